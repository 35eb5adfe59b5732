"""The scenario registry: every scenario pemviz can build a problem for, by name (as Gymnasium's ``gymnasium.register``
and ``gymnasium.make`` name environments).

A :class:`Scenario` is a small record: its name, a description, the dataclass of its parameters, a factory that
builds its :class:`pemviz.core.problems.Problem`, whether that problem carries an exact answer, and optionally the
single simulator its batched twin must match. :func:`register` adds one, :func:`registered` lists the names,
:func:`get` returns the record; ``pemviz.testing.check_scenario(name)`` checks any registered one.

A factory, a parameters dataclass or a simulator may be given as an object or as the text ``"package.module:name"``
(as Gymnasium's ``entry_point``), imported when first used, so listing the scenarios loads no PEM, no problem and no
torch."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from pemviz.methods import PLAIN_METHOD, TILT_METHOD
from pemviz.plugins import Plugins, Ref, check_record, resolve
from pemviz.scenarios.parameters import (
    KINDS,
    RANDOM_PARAMS,
    Parameter,
    ParameterError,
    changed_parameters,
    refusal,
    register_defaults,
    unit_of,
)
from pemviz.settings import REGISTERED_SCENARIOS, SCENARIO_COST_FACTORS, SCENARIO_COST_PARTS, SETTINGS


def _kind(field: dataclasses.Field) -> str:
    """``float``, ``int`` or ``bool`` for a scalar field of a dataclass (its annotation, as text or a type), else
    ``""``."""
    kind = field.type if isinstance(field.type, str) else getattr(field.type, "__name__", "")
    return kind if kind in KINDS else ""


COST_PARTS = ("step", "fit", "torch", "probe")
"""The parts of a run's cost a scenario may declare besides its rollout step (:attr:`Scenario.cost_parts`)."""


@dataclass(frozen=True)
class Scenario:
    """One scenario of the registry.

    Attributes:
        name: the registry's key (``braking``, ``toy``, ``my-robot``).
        description: one line saying what is simulated and what a failure is.
        params: the dataclass of its parameters (frozen, ``__post_init__`` raises ValueError for a value outside its
            range), or None: no parameters. A :data:`Ref`.
        factory: ``factory(config, params) -> Problem``: the problem of a run of ``config`` (a
            :class:`pemviz.config.ExperimentConfig`, or None: the defaults) with the parameters ``params`` (an
            instance of :attr:`params`, or None). A :data:`Ref`.
        exact: whether its problem carries an exact answer (``Problem.exact_log_p``) at its default parameters.
        simulator: optional, ``simulator(params) -> Simulator``: the single black-box simulator
            (:class:`pemviz.core.rollouts.Simulator`) whose rollouts the batched twin must reproduce bit for bit. A
            :data:`Ref`.
        defaults: optional, ``defaults() -> params``: the parameters at the scenario's defaults (None:
            ``params()``). A :data:`Ref`.
        drawing: optional, ``drawing(params) -> object``: the scenario's drawing object
            (:class:`pemviz.core.drawing.Drawing`), which the panel draws before any run. A :data:`Ref`.
        cost_factor: the cost of one rollout step relative to the cost model's reference
            (:mod:`pemviz.engine.cost`), > 0 (default 1).
        cost_parts: the relative cost of the scene's other parts, each > 0: ``step`` (a batch's fixed cost per time
            step), ``fit`` (a proposal's fit), ``torch`` (its fits run on torch), ``probe`` (its pilot of plain
            rollouts against its run, :func:`pemviz.engine.cost.pilot_seconds`); empty: none.
        random_params: the parameters that may be drawn per rollout over an operating design domain (``--param
            NAME~DIST``, :mod:`pemviz.scenarios.odd`); empty: none.
        odd: ``odd(config, params, odd) -> Problem``: the problem over the ODD (:class:`pemviz.core.odd.ODD`) of the
            parameters in :attr:`random_params` (:func:`pemviz.core.odd_rollouts.odd_rollout_functions`). A
            :data:`Ref`; None: no ODD.
        n_objects: the objects its problem perceives a step at its defaults, checked against a method before
            anything is loaded.
        run_defaults: the settings a run of it takes when neither a method nor a preset is asked for, e.g.
            ``{"method": "mc", "n_per_stage": 50_000}``; empty: the config's defaults.
        odd_defaults: those settings over an operating design domain, in place of :attr:`run_defaults`; empty:
            :attr:`run_defaults`.
        beyond: one line saying why no shipped method answers at the scene's rarity, shown with a run's ``next:``
            advice when its verdict is not ``reliable``; empty: one does."""

    name: str
    description: str
    params: Ref
    factory: Ref
    exact: bool = False
    simulator: Ref = None
    defaults: Ref = None
    drawing: Ref = None
    cost_factor: float = 1.0
    cost_parts: Mapping[str, float] = dataclasses.field(default_factory=dict)
    random_params: tuple[str, ...] = ()
    odd: Ref = None
    n_objects: int = 1
    run_defaults: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    odd_defaults: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    beyond: str = ""

    def __post_init__(self) -> None:
        check_record("Scenario", self.name, self.description)
        if not isinstance(self.beyond, str) or "\n" in self.beyond:
            raise ValueError(f"Scenario {self.name}: beyond must be one line of text (empty: a method answers)")
        if self.factory is None:
            raise ValueError(f"Scenario {self.name}: a factory (config, params) -> Problem is needed")
        if isinstance(self.n_objects, bool) or not isinstance(self.n_objects, int) or self.n_objects < 1:
            raise ValueError(f"Scenario {self.name}: n_objects must be an integer >= 1, got {self.n_objects!r}")
        factor = self.cost_factor
        if isinstance(factor, bool) or not isinstance(factor, (int, float)) or not 0.0 < factor < float("inf"):
            raise ValueError(f"Scenario {self.name}: cost_factor must be a finite number > 0, got {factor!r}")
        for part, value in dict(self.cost_parts).items():
            if part not in COST_PARTS or isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ValueError(
                    f"Scenario {self.name}: cost_parts takes {', '.join(COST_PARTS)} with numbers > 0, got {part!r}: "
                    f"{value!r}"
                )
            if not 0.0 < value < float("inf"):
                raise ValueError(
                    f"Scenario {self.name}: cost_parts[{part!r}] must be a finite number > 0, got {value!r}"
                )

    def params_class(self) -> type | None:
        """The dataclass of the parameters (:attr:`params` imported), or None."""
        return resolve(self.params)

    def default_params(self) -> Any:
        """The parameters at the scenario's defaults (an instance of :meth:`params_class`), or None without them."""
        if self.defaults is not None:
            return resolve(self.defaults)()
        cls = self.params_class()
        return None if cls is None else cls()

    def parameters(self) -> tuple[Parameter, ...]:
        """The parameters a user can set: every float, int and bool field of the dataclass, in field order, with the
        scenario's default and the unit its name's suffix says (:mod:`pemviz.scenarios.parameters`); ``()`` without
        a dataclass."""
        params = self.default_params()
        if params is None:
            return ()
        return tuple(
            Parameter(f.name, _kind(f), getattr(params, f.name), unit_of(f.name))
            for f in dataclasses.fields(params)
            if _kind(f)
        )

    def build_params(self, values: Mapping[str, object] | None = None) -> Any:
        """The parameters with ``values`` (name -> value) replacing the scenario's defaults; None without a dataclass
        (then ``values`` must be empty).

        Raises:
            ParameterError: a ValueError: an unknown name (the message lists the scenario's), a value not of its
                field's kind, or a value the dataclass refuses (its own message, led by the scenario's name:
                :func:`pemviz.scenarios.parameters.refusal`)."""
        values = dict(values or {})
        found = {p.name: p for p in self.parameters()}
        changes = {}
        for name, value in values.items():
            if name not in found:
                allowed = ", ".join(found) or "none"
                raise ParameterError(f"{name!r} is not a parameter of the {self.name} scenario; use one of {allowed}")
            changes[name] = found[name].check(value)
        params = self.default_params()
        if params is None:
            return None
        try:
            return dataclasses.replace(params, **changes)
        except ValueError as exc:
            raise refusal(self.name, params, exc) from None

    def problem(self, config: Any = None, params: Mapping[str, object] | None = None) -> Any:
        """The :class:`pemviz.core.problems.Problem` of this scenario for ``config`` (a
        :class:`pemviz.config.ExperimentConfig`; None: the factory's defaults) with the parameters ``params`` (name
        -> value; None: the config's where it is one of this scenario, else the scenario's defaults).

        Raises:
            ValueError: parameters the scenario refuses (:class:`pemviz.scenarios.parameters.ParameterError`).
            pemviz.pem.network.PemFormatError, OSError: the config's PEM cannot be read."""
        from pemviz.scenarios.odd import split_odd
        from pemviz.scenarios.parameters import representative

        cfg = config
        given = dict(cfg.scenario_params) if cfg is not None and cfg.scenario == self.name else {}
        values = {**given, **dict(params or {})}
        _, odd = split_odd(values.items())
        built = self.build_params(representative(self.name, values.items()) if odd is not None else values)
        if odd is not None:  # parameters drawn per rollout over an operating design domain
            return self.odd_problem(cfg, built, odd)
        return resolve(self.factory)(cfg, built)

    def odd_problem(self, config: Any, params: Any, odd: Any) -> Any:
        """The problem over the ODD ``odd`` (:attr:`odd`), the other parameters fixed at ``params``; one whose factory
        did not mark it as over ``odd`` is marked (:func:`pemviz.core.odd_rollouts.marked_over_odd`).

        Raises:
            ValueError: the scenario draws no parameter per rollout, or not one of ``odd``'s."""
        others = [name for name in odd.names if name not in self.random_params]
        if self.odd is None or others:
            raise ValueError(f"the {self.name} scenario cannot draw {', '.join(others or odd.names)} per rollout")
        from pemviz.core.odd_rollouts import marked_over_odd  # torch-free, but only a run over an ODD needs it

        return marked_over_odd(resolve(self.odd)(config, params, odd), odd)

    def single_simulator(self, params: Any = None) -> Any:
        """A new single black-box simulator of the scenario at ``params`` (None: its defaults), or None when it has
        none (:attr:`simulator`)."""
        if self.simulator is None:
            return None
        return resolve(self.simulator)(self.default_params() if params is None else params)

    def drawing_object(self, params: Any = None) -> Any:
        """The scenario's drawing object at ``params`` (None: its defaults), or None when it has none
        (:attr:`drawing`)."""
        if self.drawing is None:
            return None
        return resolve(self.drawing)(self.default_params() if params is None else params)


_REGISTRY: dict[str, Scenario] = {}


def register(scenario: Scenario, *, replace: bool = False) -> Scenario:
    """Add ``scenario`` to the registry under its name; returns it.

    Raises:
        TypeError: not a :class:`Scenario`.
        ValueError: the name is taken and ``replace`` is not given."""
    if not isinstance(scenario, Scenario):
        raise TypeError(f"register: a Scenario is needed, got {type(scenario).__name__}")
    if scenario.name in _REGISTRY and not replace:
        raise ValueError(
            f"register: a scenario named {scenario.name!r} is registered already (replace=True to " "replace it)"
        )
    _REGISTRY[scenario.name] = scenario
    SCENARIO_COST_FACTORS[scenario.name] = float(scenario.cost_factor)  # the engine's cost model reads it there
    SCENARIO_COST_PARTS[scenario.name] = {k: float(v) for k, v in dict(scenario.cost_parts).items()}
    RANDOM_PARAMS[scenario.name] = tuple(scenario.random_params)  # what --param NAME~DIST may draw
    if scenario.name not in REGISTERED_SCENARIOS:  # the settings and parameters below the registry learn of it
        REGISTERED_SCENARIOS.append(scenario.name)
    register_defaults(scenario.name, scenario.default_params, tuple(scenario.random_params))
    return scenario


def unregister(name: str) -> None:
    """Remove the scenario ``name`` from the registry (e.g. one a test registered).

    Raises:
        KeyError: no scenario of that name."""
    if name not in _REGISTRY:
        raise KeyError(f"unregister: no scenario named {name!r}; registered: {', '.join(_REGISTRY)}")
    del _REGISTRY[name]
    SCENARIO_COST_FACTORS.pop(name, None)
    SCENARIO_COST_PARTS.pop(name, None)
    if name in REGISTERED_SCENARIOS:
        REGISTERED_SCENARIOS.remove(name)
    register_defaults(name, None)


ENTRY_POINTS = "pemviz.scenarios"
"""The entry-point group through which an installed package adds its scenarios (as pytest's plugins do): in its
``pyproject.toml``, ``[project.entry-points."pemviz.scenarios"] my-robot = "my_robot.scenario:register_all"``; the
object named is a :class:`Scenario` (registered as it is) or a callable that registers its scenarios."""

PLUGIN_VARIABLE = "PEMVIZ_SCENARIOS"
"""The environment variable naming modules to import (comma-separated, ``my_robot.scenario``) before the registry is
read, each registering its scenarios when imported: a scenario of one's own without installing a package."""


class ScenarioPluginError(ValueError):
    """A scenario plugin (an entry point of :data:`ENTRY_POINTS` or a module of :data:`PLUGIN_VARIABLE`) that cannot
    be loaded: which, and why, in one line."""


def load_plugins() -> None:
    """Register the scenarios of the installed packages' entry points (:data:`ENTRY_POINTS`) and of the modules named
    by :data:`PLUGIN_VARIABLE`, once per process (:func:`registered` and :func:`get` call it).

    Raises:
        ScenarioPluginError: a plugin that cannot be imported or that raised while registering (the next call tries
            again)."""
    _PLUGINS.load()


_PLUGINS = Plugins(
    PLUGIN_VARIABLE, ENTRY_POINTS, "scenario", ScenarioPluginError, Scenario, _REGISTRY, lambda record: register(record)
)


def registered() -> tuple[str, ...]:
    """The names of every registered scenario, built-in ones first, in the order they were registered (plugins
    loaded first: :func:`load_plugins`).

    Raises:
        ScenarioPluginError: a plugin that cannot be loaded."""
    load_plugins()
    return tuple(_REGISTRY)


def described() -> tuple[tuple[str, str], ...]:
    """``(name, what it simulates)`` for every registered scenario in :func:`registered`'s order: its description up
    to the first ``;`` (the failure it counts follows there), `` (exact answer)`` where it has one. The command line's
    help and the panel's hint list the scenarios from here. A plugin that cannot be loaded leaves the scenarios
    registered so far and its one line as a last pair ``("not listed", message)``: help is still shown."""
    trouble: tuple[tuple[str, str], ...] = ()
    try:
        names = registered()
    except ScenarioPluginError as exc:
        names, trouble = tuple(_REGISTRY), (("not listed", str(exc)),)
    rows = tuple(
        (n, _REGISTRY[n].description.split(";")[0].strip() + (" (exact answer)" if _REGISTRY[n].exact else ""))
        for n in names
    )
    return rows + trouble


def scenario_hint() -> str:
    """The ``--scenario`` flag's help and the panel's scenario hint: the setting's (``the scenario, one of braking,
    cut-in, ...: what is simulated ...``), then each registered scenario and what it simulates (:func:`described`)."""
    rows = described()  # first: the plugins' scenarios join the setting's list of names
    return "; ".join((SETTINGS["scenario"].hint, *(f"{name}: {what}" for name, what in rows)))


def get(name: str) -> Scenario:
    """The scenario registered as ``name`` (plugins loaded first: :func:`load_plugins`).

    Raises:
        KeyError: no scenario of that name (the message lists the registered ones).
        ScenarioPluginError: a plugin that cannot be loaded."""
    return _PLUGINS.get(name)  # type: ignore[no-any-return]


def known(name: str) -> Scenario | None:
    """The scenario registered as ``name`` so far (plugins not loaded: a config's checks call it), or None."""
    return _REGISTRY.get(name)


def no_method_answers(scenario: str, params: Any, est: Any) -> str | None:
    """The ``next:`` line of a non-``reliable`` run of ``scenario`` with ``params`` (a config's ``scenario_params``)
    and estimate ``est`` on a scene at its defaults whose rarity no shipped method answers
    (:attr:`Scenario.beyond`): that, why, and the bound the run has; None elsewhere."""
    from pemviz.core.estimate import format_probability

    record = known(scenario or "")
    if record is None or not record.beyond or est.verdict == "reliable":
        return None
    if changed_parameters(record.name, params or ()):
        return None  # another scene than the one the record speaks of
    if est.plain_mc and est.n_failures == 0:
        bound = f"p < {format_probability(est.log_ci[1], 2)} (95 %, {est.n:,} rollouts without a failure)"
    elif est.interval_backed:
        bound = f"p in {est.interval_text()} (95 %)"
    else:
        bound = est.bound_text()
    return f"no method shipped today answers at this scene's rarity: {record.beyond}; the bound this run has: {bound}"


def problem_for(config: Any) -> Any:
    """The :class:`pemviz.core.problems.Problem` a run of ``config`` estimates, for any registered scenario
    (``config.scenario``), built-in or a plugin's alike: its factory with the config (:meth:`Scenario.problem`).

    Raises:
        KeyError: an unregistered scenario; ScenarioPluginError: a plugin that cannot be loaded; what
            :meth:`Scenario.problem` raises (parameters refused, a PEM that cannot be read)."""
    return get(config.scenario).problem(config)


_CUT_IN_COST_FACTOR = 6.7
"""A cut-in rollout step costs 6.7 braking ones (``benchmarks/calibrate_cost.py``)."""

_CUT_IN_COST_PARTS = {"probe": 2.52}
"""A cut-in pilot's CPU seconds over the model's, where its tilt's and its streamed plain rollouts' take the model's
(``benchmarks/calibrate_cost.py --probe cut-in cut-in-mc``: 2.75 and 2.80 at load average 7-9; the shipped 3.84 in
the tilt's units before they were measured against streamed plain rollouts)."""

_CROSSING_COST_FACTOR = 4.0
"""A crossing rollout step costs 4 braking ones (``benchmarks/time_estimates.py`` checks it)."""

_CROSSING_COST_PARTS = {"step": 9.0, "fit": 1.55, "torch": 1.0, "probe": 0.81}
"""A crossing batch's fixed cost per time step, its fits, its torch import and its pilot of plain rollouts, relative
to the model's (``benchmarks/calibrate_cost.py --parts`` and ``--probe``)."""


def _cut_in(name: str, rarity: str, defaults: str, **more: Any) -> Scenario:
    """A cut-in scene: the highway scenario at one rarity setting (``defaults``: its parameters' factory)."""
    return Scenario(
        name,
        f"ACC on a tracker, cars on a 3-lane highway, one cutting in at the {rarity} rarity setting; failure: a "
        "collision or the safe distance of rule R_G1",
        "pemviz.scenarios.cut_in.scenario:CutInParams",
        "pemviz.scenarios.problems:cut_in_run_problem",
        simulator="pemviz.scenarios.cut_in.highway:CutInScenario",
        defaults=f"pemviz.scenarios.cut_in.scenario:{defaults}",
        drawing="pemviz.scenarios.cut_in.drawing:CutInDrawing",
        cost_factor=_CUT_IN_COST_FACTOR,
        cost_parts=_CUT_IN_COST_PARTS,
        random_params=("cut_in_gap_m",),
        odd="pemviz.scenarios.cut_in.odd:cut_in_odd_problem",
        n_objects=5,
        **more,
    )


# run_defaults: on the cut-in and crossing scenes the adaptive sampler's estimates are orders of magnitude low (the
# user guide's Validation page), so the cut-in runs its own tilt, and where no proposal applies (an ODD, the rare
# cut-in, the crossing) plain Monte Carlo, whose Clopper-Pearson bound holds whatever p.


for _scenario in (
    Scenario(
        "braking",
        "automated braking behind a lead car, the PEM as the camera's detector; failure: the gap "
        "drops below the crash gap",
        "pemviz.scenarios.braking.simulator:BrakingParams",
        "pemviz.scenarios.problems:braking_run_problem",
        exact=True,
        simulator="pemviz.scenarios.braking.simulator:BrakingScenario",
        drawing="pemviz.scenarios.braking.drawing:BrakingDrawing",
        random_params=("gap0_m", "ego_speed0_mps"),
        odd="pemviz.scenarios.braking.odd:braking_odd_problem",
    ),
    _cut_in(
        "cut-in",
        "moderate (about 9e-5)",
        "moderate_params",
        run_defaults={"method": TILT_METHOD, "n_per_stage": 7_280},
        odd_defaults={"method": PLAIN_METHOD, "n_per_stage": 100_000},
    ),
    _cut_in(
        "cut-in-rare",
        "rare (about 1e-7)",
        "rare_params",
        run_defaults={"method": PLAIN_METHOD, "n_per_stage": 5_000},
        beyond=(
            "p is about 1e-7, a provisional figure (no reference; 10 tilted runs gave 1.8e-7, every one unreliable): "
            "plain Monte Carlo needs some 10^9 rollouts for a 20 % interval, and the tilt's and the cross-entropy "
            "sampler's weights back no interval here, single runs orders of magnitude apart "
            "(docs/cut-in.md, Limits)"
        ),
    ),
    Scenario(
        "toy",
        "toy braking: a car from an obstacle, a detection within the braking range stops it; failure: "
        "closer than the safe distance (closed-form answer)",
        "pemviz.scenarios.toy:ToyParams",
        "pemviz.scenarios.builtin:toy",
        exact=True,
        simulator="pemviz.scenarios.toy:ToyBraking",
        random_params=("braking",),
        odd="pemviz.scenarios.toy.odd:toy_odd_problem",
    ),
    Scenario(
        "crowd",
        "toy braking toward several obstacles, each detected and its distance mislocated; failure: "
        "closer than the safe distance to the nearest (closed-form answer)",
        "pemviz.scenarios.crowd.simulator:CrowdParams",
        "pemviz.scenarios.builtin:crowd",
        exact=True,
    ),
    Scenario(
        "crossing",
        "an emergency brake on tracked pedestrians stepping onto a crossing, the shipped PEMs as the "
        "camera's detector and mislocation; failure: a collision",
        "pemviz.scenarios.crossing.scene:CrossingParams",
        "pemviz.scenarios.crossing.problem:crossing",
        cost_factor=_CROSSING_COST_FACTOR,
        cost_parts=_CROSSING_COST_PARTS,
        random_params=("brake_ttc_s", "brake_mps2"),
        odd="pemviz.scenarios.crossing.odd:crossing_odd_problem",
        odd_defaults={"method": PLAIN_METHOD, "n_per_stage": 200_000},
    ),
):
    register(_scenario)
del _scenario
