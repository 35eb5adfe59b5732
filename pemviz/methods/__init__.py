"""The method registry: every estimation method a run can name, the built-in ones and a user's own, registered alike
(as :mod:`pemviz.scenarios.registry` registers scenarios, and as Gymnasium's ``register`` names environments).

A user's method joins from a module named by the environment variable :data:`PLUGIN_VARIABLE` (comma-separated, each
module registering at import) or an entry point of the group :data:`ENTRY_POINTS` (:func:`load_method_plugins`); then
the command line, the panel, ``pemviz validate`` and ``pemviz.testing.check_estimator`` take it as a built-in one.

This module imports no estimator: a builder (and every hook) may be given as the text ``"package.module:name"``
(imported when first used), so listing the methods loads no torch and the registry sits below the config and the
estimators (``scripts/import_cycles.py`` checks the layers). Each built-in method's settings are a light frozen
dataclass in a module of this package."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from pemviz.methods.rows import ROW as ROW
from pemviz.methods.rows import setting as setting
from pemviz.plugins import Plugins, Ref, check_record, resolve

PLUGIN_VARIABLE = "PEMVIZ_METHODS"
"""The environment variable naming modules (comma-separated) that register methods when imported."""

ENTRY_POINTS = "pemviz.methods"
"""The entry-point group of installed packages' methods: each a :class:`Method`, or a callable that registers some."""


class MethodPluginError(ValueError):
    """A method plugin that cannot be loaded, or raised while registering (one line naming it)."""


@dataclass(frozen=True)
class Method:
    """One estimation method of the registry.

    Attributes:
        name: the registry's key (``adaptive``, ``mc``, ``my-method``): what ``--method`` names.
        description: one line saying what it does (the command line's help and the panel's hint).
        build: ``build(config, problem, check) -> Estimator``: the estimator of a run of ``config`` (a
            :class:`pemviz.config.ExperimentConfig`: its seed, budget ``n_per_stage``, ``weights_until_failure``)
            on ``problem`` (:class:`pemviz.core.problems.Problem`); ``check`` is None or a callable the estimator may
            call between fits (it raises to cancel the run). The estimator follows the interface of
            :class:`pemviz.estimators.base.Estimator`. A :data:`Ref`.
        plan: optional, ``plan(config) -> RunPlan``: the stages the estimator will state, known before it is built
            (None: one final batch of ``config.n_per_stage``). A :data:`Ref`.
        weighted: the estimate is a mean of importance weights, so the run's rollouts can be saved
            (``--save-rollouts``) and re-estimated (``pemviz estimate``); False for splitting, which keeps none.
        extensible: final batches can be added to it until a relative precision or a decision on a requirement
            (``--rel-error``, ``--require``; :class:`pemviz.estimators.precision.PrecisionTarget`).
        plain: it draws every rollout from the target itself (q = p, weights 1): plain Monte Carlo, whose own speed
            is a plain rollout's and whose failures are binomial (the console's advice, the requirement's decision).
        array_rqmc: its batches may be drawn by Array-RQMC (``ExperimentConfig.uniforms``); False for i.i.d.
            particles (splitting).
        then: optional, ``then(estimator, config, problem) -> Estimator``: what runs after the method's stages,
            wrapping the built estimator (e.g. :mod:`pemviz.estimators.fallback`). A :data:`Ref`.
        then_most: optional, ``then_most(config, simulations) -> (n, words)``: the most simulations :attr:`then` may
            add after the planned ``simulations``, and the cost line's words for them; None: nothing. A :data:`Ref`.
        then_plan: optional, ``then_plan(config) -> RunPlan | None``: the stages :attr:`then` runs once more before
            any plain rollouts, for the time estimates (:func:`pemviz.engine.cost.follow_on`). A :data:`Ref`.
        then_drawn: optional, ``then_drawn(config, simulations, problem) -> (plan | None, n, words)``:
            :attr:`then_plan` and :attr:`then_most` on a known ``problem`` (a :class:`~pemviz.core.problems.Problem`
            or the run's :class:`~pemviz.engine.events.RunStarted`); None: those whatever the problem. A :data:`Ref`.
        validate: optional, ``validate(config, n_objects) -> (setting, what is allowed) | None``: the first of the
            method's own settings that conflicts with another in ``config`` (its scene perceiving ``n_objects``
            objects a step), checked when the config is made; None: none. A :data:`Ref`.
        more_budget: optional, ``more_budget(config, text) -> str | None``: the method's own route to a decided
            answer after a run that is not ``reliable`` (the console's ``next:`` line; ``text`` is
            :class:`pemviz.sinks.console.AdviceText`, the run's figures and the wording helpers); None: more rollouts
            or a precision target. A :data:`Ref`.
        no_failure_advice: optional, ``no_failure_advice(n) -> str``: what to try after a run of ``n`` rollouts
            without a failure (the panel's); None: more rollouts or the adaptive method. A :data:`Ref`.
        cost_model: how :mod:`pemviz.engine.cost` predicts a stage's seconds: ``plain`` (rollouts of a detector),
            ``proposal`` (a learned proposal's rollouts and its cross-entropy fits), ``look-ahead`` (rollouts whose
            steps are tilted by look-aheads, solved once) or ``splitting`` (continued particles).
        run_adds: what the run's simulations count besides the rollouts it plans (the cost line's words, e.g.
            ``plus the branches' continuations``); empty: nothing.
        proposal_curves: each stage ends with a fitted proposal whose q(detect | d) curve is worth keeping (a
            validation study's curves).
        feature_view: its stages' proposals read the state the stack acts on (:mod:`pemviz.core.feature_view`).

        describe: optional, ``describe(config, plan, window) -> str``: one Markdown sentence on a run of ``config``
            and its :class:`~pemviz.core.plan.RunPlan` (``window``: the sampler window's words), the recording's
            description of the method; None: its plan's stages. A :data:`Ref`.
        sampler: the name a rollout file records for the fixed sampler the method draws by (``pem``, ``naive50``,
            ``mixed50``: :data:`pemviz.io.rollout_format.SAMPLERS`); None: a fitted proposal or none.
        baseline: a validation study may compare it with the cross-entropy sampler at an equal budget
            (:data:`pemviz.studies.validation.BASELINES`).
        settings: optional, the method's own settings: a frozen dataclass (best a subclass of
            :class:`pemviz.settings.MethodSettings`) whose fields, each made by :func:`pemviz.settings.setting`, are its
            rows of the settings table: the config holds, records and checks them, ``pemviz run`` takes each as a
            flag (:attr:`pemviz.config.ExperimentConfig.method_settings`). A :data:`Ref` (:meth:`settings_class`).
    Raises:
        ValueError: an empty name, a name with spaces around it, or a description of several lines."""

    name: str
    description: str
    build: Ref
    plan: Ref = None
    weighted: bool = True
    extensible: bool = True
    plain: bool = False
    array_rqmc: bool = True
    validate: Ref = None
    more_budget: Ref = None
    no_failure_advice: Ref = None
    cost_model: str = "plain"
    run_adds: str = ""
    proposal_curves: bool = False
    feature_view: bool = False
    then: Ref = None
    then_most: Ref = None
    then_plan: Ref = None
    then_drawn: Ref = None
    describe: Ref = None
    sampler: str | None = None
    baseline: bool = False
    settings: Ref = None

    def __post_init__(self) -> None:
        check_record("Method", self.name, self.description)
        if self.build is None:
            raise ValueError(f"Method {self.name}: a builder (config, problem, check) -> Estimator is needed")
        if not isinstance(self.settings, str):  # a text is checked when it is first read
            self.settings_class()
        if self.cost_model not in COST_MODELS:
            raise ValueError(
                f"Method {self.name}: cost_model must be one of {', '.join(COST_MODELS)}, got " f"{self.cost_model!r}"
            )

    def settings_class(self) -> type | None:
        """The method's own settings class (:attr:`settings`, imported where a text names it), or None.

        Raises:
            ValueError: not a frozen dataclass. ImportError, AttributeError: a text naming nothing."""
        if self.settings is None:
            return None
        cls = resolve(self.settings)
        params = getattr(cls, "__dataclass_params__", None)
        if not (isinstance(cls, type) and params and params.frozen):
            raise ValueError(f"Method {self.name}: settings must be a frozen dataclass, got {cls!r}")
        return cls

    def conflict(self, config: Any, n_objects: int) -> tuple[str, str] | None:
        """(setting, what is allowed) of the first of this method's settings in ``config`` that conflicts with
        another (:attr:`validate`), or None."""
        return None if self.validate is None else resolve(self.validate)(config, n_objects)

    def builder(self) -> Callable[..., Any]:
        """The builder (:attr:`build` imported)."""
        return resolve(self.build)

    def run_plan(self, config: Any) -> Any:
        """The :class:`pemviz.core.plan.RunPlan` a run of ``config`` states before the estimator is built."""
        if self.plan is not None:
            return resolve(self.plan)(config)
        run_plan = resolve(
            "pemviz.core.plan:RunPlan"
        )  # by its path: the core (its stage kinds) sits above the registry
        return run_plan.of([(1, "final", int(config.n_per_stage))])


COST_MODELS = ("plain", "proposal", "look-ahead", "splitting")
"""The kinds of stage :mod:`pemviz.engine.cost` can predict the seconds of (:attr:`Method.cost_model`)."""

_REGISTRY: dict[str, Method] = {}
_BUILTIN: list[str] = []


def register_method(method: Method, *, replace: bool = False) -> Method:
    """Add ``method`` to the registry (returned).

    Raises:
        TypeError: not a :class:`Method`; ValueError: the name is taken (``replace=True`` replaces a method of one's
            own; a built-in one is never replaced)."""
    if not isinstance(method, Method):
        raise TypeError(f"register_method: expected a Method, got {type(method).__name__}")
    if method.name in _BUILTIN and _REGISTRY[method.name] is not method:
        raise ValueError(f"method {method.name!r} is built in; name yours otherwise")
    if method.name in _REGISTRY and not replace:
        raise ValueError(f"method {method.name!r} is already registered (replace=True replaces it)")
    _REGISTRY[method.name] = method
    return method


def unregister_method(name: str) -> None:
    """Remove a method of one's own (a test's); the built-in ones stay.

    Raises:
        ValueError: a built-in method; KeyError: no method of that name."""
    if name in _BUILTIN:
        raise ValueError(f"method {name!r} is built in and stays registered")
    del _REGISTRY[name]


def load_method_plugins() -> None:
    """Register the methods of the modules named by :data:`PLUGIN_VARIABLE` and of the installed packages' entry
    points (:data:`ENTRY_POINTS`), once per process.

    Raises:
        MethodPluginError: a plugin that cannot be imported or that raised while registering (the next call tries
            again)."""
    _PLUGINS.load()


_PLUGINS = Plugins(
    PLUGIN_VARIABLE,
    ENTRY_POINTS,
    "method",
    MethodPluginError,
    Method,
    _REGISTRY,
    lambda record: register_method(record),
)


def method_names() -> tuple[str, ...]:
    """Every registered method's name, the built-in ones first (plugins loaded first: :func:`load_method_plugins`).

    Raises:
        MethodPluginError: a plugin that cannot be loaded."""
    load_method_plugins()
    return tuple(_REGISTRY)


def registered_name(method: str | Method, who: str = "method") -> str:
    """The name of ``method``, registered: a registered name as it is, a :class:`Method` of one's own registered now
    (replacing one of its name that is not built in) and kept.

    Raises:
        ValueError: a name no one registered (the message lists the registered ones), or a built-in name for a
            method of one's own."""
    if isinstance(method, Method):
        if _REGISTRY.get(method.name) is not method:
            register_method(method, replace=True)
        return method.name
    names = method_names()
    if method not in names:
        raise ValueError(f"{who}: unknown method {method!r}; use one of {', '.join(names)}")
    return str(method)


def records() -> tuple[Method, ...]:
    """The registered methods' records, the built-in ones first, no plugin loaded."""
    return tuple(_REGISTRY.values())


def registered_names() -> tuple[str, ...]:
    """The names registered in this process, the built-in ones first, no plugin loaded (what a config may name)."""
    return tuple(_REGISTRY)


def extensible_names() -> tuple[str, ...]:
    """The registered methods final batches can be added to (:attr:`Method.extensible`), in registration order."""
    return tuple(name for name, record in _REGISTRY.items() if record.extensible)


def method_or_none(name: str) -> Method | None:
    """The registered :class:`Method` called ``name``, or None (no plugins loaded: the names a config already
    checked)."""
    return _REGISTRY.get(name)


def get_method(name: str) -> Method:
    """The registered :class:`Method` called ``name`` (plugins loaded first).

    Raises:
        KeyError: no method of that name (the message lists the registered ones); MethodPluginError: a plugin that
            cannot be loaded."""
    return _PLUGINS.get(name)  # type: ignore[no-any-return]


CROSS_ENTROPY_METHOD = "adaptive"
"""The cross-entropy sampler of Innes & Ramamoorthy (2022), Algorithm 1 (:mod:`pemviz.methods.adaptive`)."""
DEFAULT_METHOD = CROSS_ENTROPY_METHOD
"""The method a run uses where neither it nor a scenario's defaults name one."""
PLAIN_METHOD = "mc"
"""Plain Monte Carlo: what the fallback draws, and what the advice routes a run to where it decides (its record is
:attr:`Method.plain`)."""
NAIVE_METHOD = "naive50"
"""The paper's fixed 50 % detector (Table II's baseline)."""
MIXED_METHOD = "mixed50"
"""The paper's 50 % detector inside the window."""
SPLITTING_METHOD = "ams"
"""Adaptive multilevel splitting (its stages' kind is :data:`pemviz.methods.ams.AMS_STAGE`)."""
TILT_METHOD = "tilt"
"""The scenario's own tilted proposal (a scenario's default where it offers one)."""
STATE_METHOD = "state"
"""The cross-entropy sampler whose proposal reads the state the stack acts on (:mod:`pemviz.methods.state`)."""


def _cross_entropy(name: str, description: str, build: str, **more: Any) -> Method:
    """A cross-entropy sampler's record: its stages, budget, advice and cost are the adaptive method's."""
    return Method(
        name,
        description,
        build,
        plan="pemviz.estimators.ce_plan:adaptive_run_plan",
        validate="pemviz.estimators.builtin:adaptive_conflict",
        more_budget="pemviz.estimators.builtin:adaptive_more_budget",
        no_failure_advice="pemviz.estimators.builtin:adaptive_no_failure",
        cost_model="proposal",
        then="pemviz.estimators.fallback:with_plain_fallback",
        then_most="pemviz.estimators.builtin:adaptive_then_most",
        then_plan="pemviz.estimators.builtin:adaptive_then_plan",
        **more,
    )


for _record in (
    _cross_entropy(
        CROSS_ENTROPY_METHOD,
        "cross-entropy adaptive importance sampling (Algorithm 1 of Innes & Ramamoorthy 2022)",
        "pemviz.estimators.cross_entropy:CrossEntropy",
        proposal_curves=True,
        then_drawn="pemviz.estimators.builtin:adaptive_then_drawn",
        describe="pemviz.methods.words:adaptive",
        settings="pemviz.methods.adaptive:CrossEntropySettings",
    ),
    Method(
        PLAIN_METHOD,
        "rollouts with the PEM itself (plain Monte Carlo)",
        "pemviz.estimators.builtin:mc",
        plain=True,
        no_failure_advice="pemviz.estimators.builtin:mc_no_failure",
        describe="pemviz.methods.words:mc",
        sampler="pem",
        baseline=True,
    ),
    Method(
        NAIVE_METHOD,
        "a 50 % detector at every step",
        "pemviz.estimators.builtin:naive50",
        describe="pemviz.methods.words:naive50",
        sampler=NAIVE_METHOD,
        baseline=True,
    ),
    Method(
        MIXED_METHOD,
        "50 % inside the window and the PEM outside",
        "pemviz.estimators.builtin:mixed50",
        describe="pemviz.methods.words:mixed50",
        sampler=MIXED_METHOD,
        baseline=True,
    ),
    Method(
        SPLITTING_METHOD,
        "adaptive multilevel splitting on the robustness, no importance weights",
        "pemviz.estimators.ams:AdaptiveMultilevelSplitting",
        plan="pemviz.estimators.ams:AdaptiveMultilevelSplitting.run_plan",
        weighted=False,
        extensible=False,
        array_rqmc=False,
        validate="pemviz.estimators.builtin:ams_conflict",
        more_budget="pemviz.estimators.builtin:ams_more_budget",
        no_failure_advice="pemviz.estimators.builtin:ams_no_failure",
        cost_model="splitting",
        run_adds="plus the branches' continuations",
        describe="pemviz.methods.words:ams",
        baseline=True,
    ),
    Method(
        TILT_METHOD,
        "the scenario's own proposal: each step's events tilted by an approximate probability of failure after them",
        "pemviz.estimators.builtin:tilt",
        more_budget="pemviz.estimators.builtin:tilt_more_budget",
        cost_model="look-ahead",
        run_adds="plus the proposal's look-aheads",
        describe="pemviz.methods.words:tilt",
    ),
    _cross_entropy(
        STATE_METHOD,
        "cross-entropy importance sampling of each detection (and with --state-fit-errors each error's location and "
        "scale) by the object's row and the state the stack acts on (the tracker's features, the ego's); scenes that "
        "report them",
        "pemviz.estimators.state:StateCrossEntropy",
        run_adds="plus the replay of each batch's state features",
        baseline=True,
        feature_view=True,
        settings="pemviz.methods.state:StateSettings",
    ),
):
    register_method(_record)
    _BUILTIN.append(_record.name)
del _record

BUILTIN_METHODS = tuple(_BUILTIN)
"""The built-in methods' names, in the order a list of methods gives them (a user's own come after)."""
