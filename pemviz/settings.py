"""The settings table: what each :class:`pemviz.config.ExperimentConfig` setting is, in one place.

Each setting's symbol, words, range, unit, help, flag and owner is a :class:`Setting` in :data:`SETTINGS`, read by the
config's checks, the command line, the panel's form and the estimators (:func:`settings_of`); the allowed choices and
limits live beside it. The cross-entropy sampler's rows are the fields of
:class:`pemviz.methods.adaptive.CrossEntropySettings`; the fallback's those of :class:`FallbackSettings` here."""

from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass
from typing import Any

from pemviz.methods import BUILTIN_METHODS, CROSS_ENTROPY_METHOD, ROW, SPLITTING_METHOD, records, registered_names
from pemviz.methods import setting as setting  # a method's settings field and its row: here for the plugins' import
from pemviz.methods.adaptive import CrossEntropySettings

DEFAULT_MAX_SIMS = 1_000_000
"""The most simulations of a run with a stop rule (``rel_error``, ``require``) and no ``max_sims``: its stages, their
added batches, a retry and plain Monte Carlo after them together."""

METRICS = ("classic", "agm", "smooth-cumulative")
"""Robustness semantics that rank rollouts and set the adaptive thresholds (Innes & Ramamoorthy 2022, Sec. IV)."""

SIMULATORS = ("highway-env", "batched")
"""Braking-scenario back-ends (:func:`pemviz.scenarios.braking.problem.braking_problem`): ``batched`` advances all
rollouts together in numpy, ``highway-env`` steps one black-box simulator per rollout; the same seed gives the same
rollouts on both."""

DEFAULT_SCENARIO = "braking"
"""The scenario a run estimates when none is named (``--scenario``)."""

SCENARIOS = (DEFAULT_SCENARIO, "cut-in", "cut-in-rare")
"""What a run estimates (:func:`pemviz.scenarios.problems.problem_for`): ``braking``, the paper's scenario; ``cut-in``,
a car cutting in on a 3-lane highway (about 9e-5); ``cut-in-rare``, the same at about 1e-7."""


REGISTERED_SCENARIOS: list[str] = []
"""The scenarios registered in this process besides :data:`SCENARIOS` (written by
:func:`pemviz.scenarios.registry.register`): the settings read this list and never import the registry."""


SCENARIO_COST_FACTORS: dict[str, float] = {}
"""Scenario name -> how many reference rollout steps one of its rollout steps costs (written by
:func:`pemviz.scenarios.registry.register`, read by :func:`pemviz.engine.cost.stage_cost`; 1 for a name not here)."""

SCENARIO_COST_PARTS: dict[str, dict[str, float]] = {}
"""Scenario name -> the other parts of a run's cost its scene declares (:attr:`pemviz.scenarios.registry.Scenario.
cost_parts`: ``step``, ``fit``, ``torch``), written and removed as :data:`SCENARIO_COST_FACTORS` (none for a name not
here)."""


def scenario_names() -> tuple[str, ...]:
    """The scenarios a config may name: :data:`SCENARIOS`, then :data:`REGISTERED_SCENARIOS` in registration order."""
    return (*SCENARIOS, *(n for n in REGISTERED_SCENARIOS if n not in SCENARIOS))


EXECUTORS = ("local", "serial", "ray")
"""Where rollouts are simulated (:func:`pemviz.engine.executors.get_executor`): ``local`` worker processes, ``serial``
in this process, ``ray`` on a Ray cluster; the same seed gives the same rollouts and estimate, bit for bit."""

UNIFORMS = ("array-rqmc", "iid")
"""How a batch's rollouts draw their detections (:class:`~pemviz.config.ExperimentConfig` ``uniforms``)."""
AMS_SCORES = ("robustness", "lookahead", "committor")
"""What ranks the AMS particles (:class:`~pemviz.config.ExperimentConfig` ``ams_score``,
:mod:`pemviz.estimators.ams`): the formula's classic robustness, the robustness of the nominal continuation from
each step (any scene with snapshot/restore: :mod:`pemviz.estimators.lookahead_score`), or -log of the scenario's
learned committor (:mod:`pemviz.scenarios.cut_in.splitting`)."""
MAX_SEED = 2**64 - 1
"""Largest seed: torch's generator takes a 64-bit unsigned seed."""
PANEL_PLACES = ("main", "advanced")
"""Where the panel's form shows a setting (:attr:`Setting.panel`): above the fold, or in the folder *advanced*."""

RUN = "run"
"""The owner of a setting that the run itself reads, whatever its method (the engine, the problem, the seed)."""
FALLBACK = "fallback"
"""The owner of the fallback's settings (:class:`FallbackSettings`): what runs after the stages of any method whose
record has a :attr:`~pemviz.methods.Method.then` (:func:`pemviz.estimators.fallback.with_plain_fallback`)."""


RETRY_MOST_N = 10_000
"""The most rollouts of a retry's stage: a run of larger N retries at this N, and one at it or above does not retry."""


@dataclass(frozen=True)
class FallbackSettings:
    """The retry and plain Monte Carlo after a method's stages where their weights back no interval (a verdict other
    than ``reliable``), read by :class:`pemviz.estimators.fallback.PlainFallback` whatever the method. Each field, made
    by :func:`setting`, carries its row of :data:`SETTINGS` (owner :data:`FALLBACK`).

    Attributes:
    plain_fallback: plain Monte Carlo rollouts after the stages, at most this many times their simulations
        (:func:`plain_fallback_most`; capped by :data:`PLAIN_FALLBACK_MOST` and ``max_sims``), to the run's precision
        target or requirement; the run's answer is then plain Monte Carlo's where it saw a failure. 0: none. Not over
        an operating design domain.
    retry_factor: before that plain Monte Carlo, the stages once more with N this many times as large
        (:meth:`retry_n`), from a stream of their own. 0 or 1: no retry. Only with ``plain_fallback`` > 0 and no stop
        rule."""

    plain_fallback: int = setting(
        500,
        "the plain Monte Carlo fallback",
        "where the weights back no interval, plain Monte Carlo after the stages, at most this many times their "
        "simulations, to the precision target or a 20 % interval (0: none)",
        kind="int",
        lo=0,
        flags=("--plain-fallback",),
        panel="advanced",
    )
    retry_factor: int = setting(
        4,
        "the retry's factor on N",
        "where the weights back no interval, the stages once more before plain Monte Carlo, with N this many times "
        "as large, from a stream of their own (0 or 1: no retry; none without the plain Monte Carlo fallback)",
        kind="int",
        lo=0,
        flags=("--retry-factor",),
        panel="advanced",
    )

    def retry_n(self, n: int, stop_rule: str | None = None) -> int | None:
        """N of the retry of stages of ``n`` rollouts: ``n`` times ``retry_factor``, at most :data:`RETRY_MOST_N`; None
        where the run has none (``retry_factor`` < 2, ``plain_fallback`` = 0, a stop rule, or ``n`` at the most)."""
        factor, n = int(self.retry_factor), int(n)
        if factor < 2 or self.plain_fallback <= 0 or stop_rule is not None or n >= RETRY_MOST_N:
            return None
        return min(factor * n, RETRY_MOST_N)


PLAIN_FALLBACK_MOST = 1_000_000
"""The most plain rollouts the fallback draws after any run, whatever its size (``plain_fallback`` times the stages'
simulations below it: a large run of the stages gets no larger fallback)."""


def plain_fallback_most(ratio: int, spent: int, max_sims: int | None = None) -> int:
    """The most plain rollouts the fallback draws after stages that simulated ``spent`` rollout-equivalents: ``ratio``
    times ``spent`` (at least 1), at most :data:`PLAIN_FALLBACK_MOST` and what ``max_sims`` leaves; 0 when ``ratio``
    <= 0 or nothing is left."""
    if ratio <= 0:
        return 0
    most = min(int(ratio) * max(1, int(spent)), PLAIN_FALLBACK_MOST)
    if max_sims is not None:  # the run's own cap holds for everything it simulates
        most = min(most, int(max_sims) - int(spent))
    return max(0, most)


@dataclass(frozen=True)
class Setting:
    """What one :class:`~pemviz.config.ExperimentConfig` setting is, in the one place every reader takes it from: the
    config's checks, the command line's flags, the panel's form and the estimators (:func:`settings_of`).

    Attributes:
        name: the setting's flat name.
        words: what it is, a noun with its symbol (``"the smoothing alpha"``): ``<words> must be <allowed>``.
        help: what it does, one line, no measured figures (the flag's help and the panel's hint).
        kind: ``int``, ``real``, ``choice``, ``method`` (a registered method), ``scenario`` (a registered scenario),
            ``bool``, ``text``, ``pem`` (a shipped PEM name or a file, checked where loaded) or ``params`` (the
            scenario's parameters, :mod:`pemviz.scenarios.parameters`).
        symbol: the paper's symbol (``alpha``, ``sigma``, ``K``, ``N``, ``N_e``; ``k`` of AMS), or None.
        short: the name in the panel and the run labels when it is neither the symbol nor the words.
        unit: the unit of a physical quantity (``""``: a count, a probability or a name).
        lo, hi, lo_open, hi_open: the allowed range of a number; ``lo_open`` / ``hi_open`` exclude the end.
        hi_words: how the upper end is written (``2^64 - 1``).
        text_words: what a ``text`` setting takes, in words (``a Ray address``).
        optional: None is allowed too.
        choices: the allowed values of a ``choice``.
        choice_help: (value, what it does) for each choice.
        flags: the command-line flags, the first the one error messages name (empty: no flag).
        panel: where the panel's form shows it (:data:`PANEL_PLACES`; empty: not shown).
        owner: who reads it: :data:`RUN`, :data:`FALLBACK` or the method whose estimator reads it."""

    name: str
    words: str
    help: str
    kind: str = "real"
    symbol: str | None = None
    short: str | None = None
    unit: str = ""
    lo: float = -math.inf
    hi: float = math.inf
    lo_open: bool = False
    hi_open: bool = False
    hi_words: str | None = None
    text_words: str = "non-empty text"
    optional: bool = False
    choices: tuple[str, ...] = ()
    choice_help: tuple[tuple[str, str], ...] = ()
    flags: tuple[str, ...] = ()
    panel: str = ""
    owner: str = CROSS_ENTROPY_METHOD

    @property
    def label(self) -> str:
        """The name in the panel, the run labels and the compare table (``smoothing`` -> ``alpha``)."""
        return self.short or self.symbol or self.name.replace("_", " ")

    @property
    def integer(self) -> bool:
        return self.kind == "int"

    @property
    def flag(self) -> str:
        """The command-line flag that sets it (``--alpha``), or ``--`` + the field's name where it has none."""
        return self.flags[0] if self.flags else "--" + self.name.replace("_", "-")

    @property
    def allowed(self) -> str:
        """The allowed values in words, the same in the config's, the command line's and the form's messages:
        ``a number in (0, 1]``, ``a whole number >= 2``, ``one of classic, agm, smooth-cumulative``."""
        if self.kind == "choice":
            text = f"one of {', '.join(self.choices)}"
        elif self.kind == "method":
            text = f"one of {', '.join(registered_names())}"
        elif self.kind == "scenario":
            text = f"one of {', '.join(scenario_names())}"
        elif self.kind == "bool":
            text = "True or False"
        elif self.kind == "text":
            text = self.text_words
        elif self.kind == "pem":
            text = "a shipped PEM name or a PEM file"
        elif self.kind == "params":
            text = "NAME=VALUE, a parameter of the scenario and its value"
        elif self.integer:
            lo = int(self.lo)
            hi = self.hi_words or (None if math.isinf(self.hi) else int(self.hi))
            text = f"a whole number >= {lo}" if hi is None else f"a whole number in [{lo}, {hi}]"
        elif math.isinf(self.hi):
            text = f"a number {'>' if self.lo_open else '>='} {self.lo:g}"
        else:
            text = f"a number in {'(' if self.lo_open else '['}{self.lo:g}, {self.hi:g}{')' if self.hi_open else ']'}"
        return f"none or {text}" if self.optional else text  # none: typed as such, or the flag left out

    @property
    def hint(self) -> str:
        """The flag's help and the panel's hint: ``smoothing alpha, a number in (0, 1]: the power on ...``."""
        noun = self.words.removeprefix("the ") + (f" in {self.unit}" if self.unit else "")
        text = f"{noun}, {self.allowed}: {self.help}"
        return "; ".join((text, *(f"{value}: {what}" for value, what in self.choices_help)))

    @property
    def choices_help(self) -> tuple[tuple[str, str], ...]:
        """(value, what it does) for each choice: :attr:`choice_help`, of a ``method`` each registered method's
        :attr:`~pemviz.methods.Method.description`."""
        if self.kind != "method":
            return self.choice_help
        from pemviz.methods import records

        return tuple((record.name, record.description) for record in records())

    def accepts(self, value: object) -> bool:
        """Whether ``value`` is allowed on its own (the config also checks settings against each other)."""
        if self.kind == "pem":  # a name or a file: checked where it is loaded (no I/O here)
            return True
        if value is None:
            return self.optional
        if self.kind == "choice":
            return isinstance(value, str) and value in self.choices
        if self.kind == "method":  # a built-in one, or one a plugin has registered in this process
            return isinstance(value, str) and value in registered_names()
        if self.kind == "scenario":  # a built-in one, or one the registry has registered in this process
            return isinstance(value, str) and value in scenario_names()
        if self.kind == "bool":
            return isinstance(value, bool)
        if self.kind == "text":
            return isinstance(value, str) and value != ""
        if self.kind == "params":  # the names and values are checked against the scenario by the config
            return isinstance(value, tuple) and all(
                isinstance(x, tuple) and len(x) == 2 and isinstance(x[0], str) for x in value
            )
        if not (_is_int(value) if self.integer else _is_real(value)):
            return False
        assert isinstance(value, (int, float))  # just checked: a whole or a real number
        too_low = value <= self.lo if self.lo_open else value < self.lo
        too_high = value >= self.hi if self.hi_open else value > self.hi
        return not (too_low or too_high)

    def parse(self, text: str) -> int | float | None:
        """The number typed as ``text`` (the panel's fields, the command line's flags), its range not checked;
        ``none`` (any case) for an optional setting: None.

        Decimal and scientific notation (``0.2``, ``1e-3``, ``1e5``) with surrounding spaces; a whole-number
        setting takes only whole values (``1e5`` yes, ``12.5`` no), exactly beyond float64's 2^53. Nothing is
        rounded.

        Raises:
            ValueError: empty, not a number, not finite, or not whole where it must be; the message says what
                to type, in :attr:`allowed`'s words."""
        raw = str(text).strip()
        if self.optional and raw.lower() == "none":  # what the messages say to type for "no value"
            return None
        if raw == "":
            raise ValueError(f"empty; type {self.allowed} ({self.words})")
        if not _NUMBER.match(raw):
            raise ValueError(f"{raw!r} is not a number; type {self.allowed} ({self.words})")
        value: float | int = int(raw) if self.integer and re.fullmatch(r"[+-]?\d+", raw) else float(raw)
        if not math.isfinite(value):
            raise ValueError(f"{raw!r} is too large; type {self.allowed} ({self.words})")
        if self.integer and isinstance(value, float):
            if not value.is_integer():
                raise ValueError(f"{raw} is not a whole number; {self.words} must be {self.allowed}")
            value = int(value)
        return value

    @property
    def title(self) -> str:
        """``smoothing (alpha)``: the field and its symbol, as the config's messages name it."""
        return f"{self.name} ({self.symbol})" if self.symbol else self.name


_NUMBER = re.compile(r"^[+-]?(\d+(\.\d*)?|\.\d+)([eE][+-]?\d+)?$")


def _rows(cls: type, owner: str, skip: frozenset[str] = frozenset()) -> dict[str, Setting]:
    """The :class:`Setting` of each field of ``cls`` made by :func:`setting` but those in ``skip``, by name, in the
    fields' order."""
    fields = [f for f in dataclasses.fields(cls) if ROW in f.metadata and f.name not in skip]
    return {f.name: Setting(f.name, owner=owner, **f.metadata[ROW]) for f in fields}


def _settings(*settings: Setting | str) -> tuple[dict[str, Setting], dict[str, Setting]]:
    """The table: the run's and splitting's rows, then the cross-entropy sampler's and the fallback's, in the order runs
    have always recorded them; fields added to their settings follow every other row."""
    own = {**_rows(CrossEntropySettings, CROSS_ENTROPY_METHOD), **_rows(FallbackSettings, FALLBACK)}
    table = {s.name: s for s in (own.pop(row) if isinstance(row, str) else row for row in settings)}
    return table, own


_NAMED, _ADDED = _settings(
    Setting("method", "the method", "the estimator", kind="method", choices=BUILTIN_METHODS, owner=RUN,
            flags=("--method",)),
    "n_stages",
    Setting("n_per_stage", "the rollouts per stage N",
            "rollouts of each stage; of mc, naive50 and mixed50 all their rollouts; of ams its particles",
            kind="int", symbol="N", lo=2, owner=RUN, flags=("--n",), panel="main"),
    "n_final",
    "quantile_level",
    "smoothing",
    Setting("metric", "the robustness metric", "the semantics that ranks the rollouts and sets the stage thresholds "
            "(a failure is always a negative classic robustness)", kind="choice", choices=METRICS, short="metric",
            owner=RUN, flags=("--metric",),
            choice_help=(("classic", "the worst step's margin alone"),
                         ("agm", "every step's normalised margin, so time spent near the bound counts"),
                         ("smooth-cumulative", "a soft minimum of softplus margins, so every near-worst step counts"))),
    Setting("seed", "the seed", "seeds the rollouts, the fits, tie-breaking and the proposal's initial weights; the "
            "same seed gives the same run", kind="int", lo=0, hi=MAX_SEED, hi_words="2^64 - 1", owner=RUN,
            flags=("--seed",), panel="main"),
    "ce_epochs",
    "pretrain_rollouts",
    "pretrain_epochs",
    "learning_rate",
    "weights",
    "final_estimate",
    "pool_weights",
    Setting("uniforms", "the uniforms of a batch", "how the rollouts of a batch draw their detections; every estimate "
            "keeps its expectation", kind="choice", choices=UNIFORMS, owner=RUN,
            choice_help=(("array-rqmc", "the rollouts of a block stepped as one array on a randomly shifted lattice"),
                         ("iid", "one independent uniform per rollout and step (the paper)"))),
    Setting("pem", "the perception error model", "the PEM the rollouts detect with", kind="pem",
            short="PEM", owner=RUN, flags=("--pem",)),
    Setting("scenario", "the scenario", "what is simulated and whose failure probability is estimated",
            kind="scenario", choices=SCENARIOS, owner=RUN, flags=("--scenario",)),
    Setting("scenario_params", "the scenario's parameters", "set one of the scenario's parameters, e.g. "
            "cut_in_gap_m=25 (repeatable; the names, units and defaults: the user guide's command-line page)",
            kind="params", short="scenario parameters", owner=RUN, flags=("--param",)),
    Setting("sim", "the simulator", "the braking scenario's back-end; a seed gives the same rollouts on both",
            kind="choice", choices=SIMULATORS, short="simulator", owner=RUN, flags=("--sim",),
            choice_help=(("highway-env", "one highway-env simulator per rollout"),
                         ("batched", "all rollouts advanced together in numpy"))),
    Setting("executor", "the executor", "where rollouts are simulated; a seed gives the same rollouts and estimate, "
            "bit for bit", kind="choice", choices=EXECUTORS, owner=RUN, flags=("--executor",),
            choice_help=(("local", "worker processes on this machine (--workers) for batches whose blocks of 8192 "
                                   "rollouts pay for their start; smaller ones in this process"),
                         ("serial", "in this process"),
                         ("ray", "Ray tasks over blocks of rollouts; a batch of one block runs in this process"))),
    Setting("workers", "the workers", "the processes executor local simulates on (None: every usable core, the "
            "affinity mask and cgroup quota's; 1: this process only); a seed gives the same rollouts and estimate, bit "
            "for bit", kind="int", lo=1, optional=True, owner=RUN, flags=("--workers",)),
    Setting("ray_address", "the Ray cluster", "the cluster that executor ray uses", kind="text",
            text_words="a Ray address, e.g. ray://host:10001", optional=True, owner=RUN, flags=("--ray-address",)),
    Setting("chunk_rollouts", "the chunk size", "the most rollouts simulated and scored at a time: a serial stage of "
            "more streams chunk by chunk; a seed gives the same rollouts and estimate, bit for bit, at any chunk size",
            kind="int", lo=1, optional=True, owner=RUN, flags=("--chunk",)),
    Setting("rel_error", "the target relative error", "sample more until the 95 % interval's half-width is at most "
            "this share of the estimate, or a cap (--max-sims, --max-time) is hit (None: the planned budget only)",
            lo=0.0, hi=10.0, lo_open=True, optional=True, owner=RUN, short="rel. error", flags=("--rel-error",),
            panel="advanced"),
    Setting("require", "the requirement", "a requirement on p, e.g. 'p < 1e-9': sample more until the interval lies "
            "wholly on one side of the threshold (a sequential test whose error stays at most 5 % over every look), or "
            "a cap (--max-sims, --max-time) is hit; pemviz run exits 0 met, 1 violated, 3 undecided", kind="text",
            text_words="a requirement p < T, p <= T, p > T or p >= T with T in (0, 1), e.g. 'p < 1e-9'",
            optional=True, owner=RUN, flags=("--require",)),
    Setting("margin", "the crash gap", "braking: a failure is the gap dropping below this many metres (None: the "
            "scenario's 2 m); 0 targets a gap below 0 m, the severity curve's last point, which a run at 2 m rarely "
            "reaches (below where a never-detecting rollout ends, the last metres are enumerated exactly)",
            unit="m", lo=0.0, hi=10.0, optional=True, owner=RUN, flags=("--margin",)),
    Setting("pem_uncertainty", "the PEM's uncertainty", "re-weight the run's rollouts under each member of the "
            "PEM's bootstrap ensemble and under its logits shifted by a half and a whole unit either way: the spread "
            "of p over plausible PEMs, with no new simulation", kind="bool", owner=RUN, short="PEM uncertainty",
            flags=("--pem-uncertainty",)),
    Setting("pem_shift", "the PEM's logit shift", "re-weight the run's rollouts under the PEM with every logit "
            "shifted by D (log-odds): a camera that misses more (D < 0) or less often than the PEM says",
            lo=-10.0, hi=10.0, optional=True, owner=RUN, short="PEM shift", flags=("--pem-shift",)),
    Setting("max_sims", "the most simulations", "with a precision target (--rel-error) or a requirement (--require): "
            "the run stops adding rollouts at this many simulations in all, plain Monte Carlo after the stages "
            f"included (None: {DEFAULT_MAX_SIMS:,})", kind="int", lo=1, optional=True, owner=RUN,
            short="max sims", flags=("--max-sims",), panel="advanced"),
    Setting("max_time_s", "the most wall-clock time", "with --rel-error or --require: no more rollouts once the run "
            "has taken this long; where the run stops then depends on the machine (None: no time cap)", unit="s",
            lo=0.0, lo_open=True, optional=True, owner=RUN, short="max time", flags=("--max-time",), panel="advanced"),
    "proposal_inputs",
    "proposal_window",
    "skip_decided",
    Setting("weights_until_failure", "the weights until failure", "importance weights stop at the step where the "
            "failure happens", kind="bool", owner=RUN),
    "smoothing_at_failure",
    "final_smoothing",
    "elite_ties",
    "pretrain_cap",
    "defensive",
    "target_share",
    "plain_share",
    "fit_all_failures",
    "fit_weights",
    "fit",
    "fit_precision",
    "fit_max_steps",
    "fit_rows",
    "fit_tolerance",
    "plain_fallback",
    "retry_factor",
    Setting("ams_killed", "the particles killed per iteration k", "particles killed and resampled per AMS iteration "
            "at least (and every tie at the level); k < N", kind="int", symbol="k", lo=1, owner=SPLITTING_METHOD,
            flags=("--ams-killed",)),
    Setting("ams_max_iterations", "the most AMS iterations", "a run stopped by them before the failure level is "
            "doubtful", kind="int", lo=1, owner=SPLITTING_METHOD),
    Setting("ams_score", "the AMS score", "what ranks the AMS particles", kind="choice", choices=AMS_SCORES,
            owner=SPLITTING_METHOD, flags=("--ams-score",),
            choice_help=(("robustness", "the formula's classic robustness"),
                         ("lookahead", "the robustness of the nominal continuation from each step (any scene)"),
                         ("committor", "-log of the scenario's learned probability of failure (the cut-in's)"))),
    Setting("ams_replicas", "the splitting runs R", "whole splitting runs from streams of their own, side by side on "
            "the run's workers: the estimate is their mean, its interval from their spread (1: one run)", kind="int",
            symbol="R", lo=1,
            owner=SPLITTING_METHOD, flags=("--ams-replicas",)),
)  # fmt: skip  # a table: each setting in the few lines it reads best in, not one argument a line
SETTINGS: dict[str, Setting] = {**_NAMED, **_ADDED}
"""The :class:`Setting` of the run's, the cross-entropy sampler's, splitting's and the fallback's settings, by name."""
CROSS_ENTROPY = frozenset(f.name for f in dataclasses.fields(CrossEntropySettings))
"""The cross-entropy sampler's settings (rows of :data:`SETTINGS`), held by the adaptive and state methods' settings."""

OWN_DEFAULTS: dict[str, Any] = {
    name: value
    for record in records()
    if record.name in BUILTIN_METHODS and (kind := record.settings_class()) is not None
    for name, value in dataclasses.asdict(kind()).items()
    if name not in SETTINGS
}
"""The built-in methods' own settings but the table's (the state method's) at their defaults, by name: what a run of
another method records for them (every run has recorded them since they were the config's)."""
RECORDED: tuple[str, ...] = (*_NAMED, *OWN_DEFAULTS, *_ADDED)
"""The keys a run records its settings by (:meth:`pemviz.config.ExperimentConfig.flat`), in order: the table's rows,
the built-in methods' own settings (:data:`OWN_DEFAULTS`), then rows added to the cross-entropy sampler's settings."""


class ConfigError(ValueError):
    """An invalid experiment setting: the message says which, the value, and what is allowed.

    Attributes:
        field: the :class:`~pemviz.config.ExperimentConfig` attribute (or the method's setting) at fault (None when not
            one field)."""

    def __init__(self, message: str, field: str | None = None) -> None:
        super().__init__(message)
        self.field = field


def rows_of(cls: type, owner: str) -> dict[str, Setting]:
    """The :class:`Setting` of each field of ``cls`` (a method's settings dataclass: :func:`setting`), by name, in the
    fields' order, owned by ``owner``; of a subclass of
    :class:`~pemviz.methods.adaptive.CrossEntropySettings` (the adaptive and state methods'), the fields it adds (the
    sampler's are rows of :data:`SETTINGS`).

    Raises:
        TypeError: a field without a row (not made by :func:`setting`), or a name the settings table already has."""
    skip = CROSS_ENTROPY if issubclass(cls, CrossEntropySettings) else frozenset()
    for f in dataclasses.fields(cls):
        if f.name not in skip and (ROW not in f.metadata or f.name in SETTINGS):
            why = "is the name of a setting of pemviz" if f.name in SETTINGS else "has no row (pemviz.settings.setting)"
            raise TypeError(f"{cls.__name__}.{f.name} {why}")
    return _rows(cls, owner, skip)


def check_settings(settings: object, owner: str = "") -> None:
    """Each field of ``settings`` (a method's settings dataclass) within its row's range.

    Raises:
        ConfigError: the first that is not, in one line (the config's words: ``coin_share (eps) = 2.0 is invalid: the
            coin's share eps must be a number in (0, 1)``); TypeError: as :func:`rows_of`."""
    for s in rows_of(type(settings), owner).values():
        value = getattr(settings, s.name)
        if not s.accepts(value):
            verb = "use" if s.kind == "choice" else f"{s.words} must be"
            raise ConfigError(f"{s.title} = {value!r} is invalid: {verb} {s.allowed}", s.name)


class MethodSettings:
    """The base of a method's settings dataclass (frozen; each field made by :func:`setting`): a value out of its
    row's range is refused when the settings are made (:func:`check_settings`)."""

    def __post_init__(self) -> None:
        check_settings(self)


def settings_of(owner: str) -> tuple[str, ...]:
    """The fields of the table that ``owner`` reads (:attr:`Setting.owner`): :data:`RUN`, :data:`FALLBACK`, ``adaptive``
    or ``ams`` (a method with settings of its own, :attr:`pemviz.methods.Method.settings`, reads those:
    :func:`rows_of`)."""
    return tuple(name for name, s in SETTINGS.items() if s.owner == owner)


def _is_real(x: object) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and x == x


def _is_int(x: object) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)


def setting_of(config: object, name: str, default: object = None) -> Any:
    """The setting ``name`` (a flat name of :data:`SETTINGS`) of ``config``: an
    :class:`~pemviz.config.ExperimentConfig`'s :meth:`~pemviz.config.ExperimentConfig.value`, else its attribute
    ``name`` or ``default``: for the layers below the config, which do not import it."""
    value = getattr(config, "value", None)
    if callable(value) and name in SETTINGS:
        return value(name)
    return getattr(config, name, default)
