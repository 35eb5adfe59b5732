"""ExperimentConfig validation: one clear message naming the setting, the value and what is allowed; every setting's
one home (SETTINGS), which the config, the command line, the panel's form and the estimators read alike."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import inspect
import io
import math
import re

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pemviz.config import ConfigError, ExperimentConfig
from pemviz.presets import PRESETS
from pemviz.settings import FALLBACK, RUN, SETTINGS, settings_of


@pytest.mark.parametrize(
    "field, value, message",
    [
        ("smoothing", 0.0, r"alpha must be a number in \(0, 1\]"),
        ("smoothing", 1.5, r"alpha must be a number in \(0, 1\]"),
        ("quantile_level", 1.0, r"sigma must be a number in \[0.5, 1\)"),
        ("quantile_level", 0.4, r"sigma must be a number in \[0.5, 1\)"),
        ("n_per_stage", 1, r"N must be a whole number >= 2"),
        ("n_stages", 0, r"K must be a whole number in \[1, 1000\]"),
        ("metric", "robust", r"use one of classic, agm, smooth-cumulative"),
        ("method", "mcmc", r"use one of adaptive, mc, naive50, mixed50"),
        ("seed", -1, r"seed must be a whole number in \[0, 2\^64 - 1\]"),
    ],
)
def test_invalid_setting_is_rejected_with_its_name_value_and_range(field, value, message):
    with pytest.raises(ConfigError, match=message) as err:
        ExperimentConfig.of(**{field: value})
    assert field in str(err.value) and repr(value) in str(err.value)


def test_defaults_keep_the_papers_stages_with_a_larger_final_batch_and_count_2100_simulations():
    c = ExperimentConfig.of()
    assert (
        c.adaptive.n_stages,
        c.n_per_stage,
        c.adaptive.n_final,
        c.adaptive.quantile_level,
        c.adaptive.smoothing,
        c.metric,
        c.seed,
    ) == (
        10,
        100,
        1000,
        0.95,
        0.1,
        "classic",
        0,
    )
    assert c.n_simulations == 100 + 10 * 100 + 1000
    assert ExperimentConfig.of(**PRESETS["paper"]).n_simulations == 100 + 10 * 100 + 100  # the paper's 1,200
    assert ExperimentConfig.of(method="mc", n_per_stage=10000).n_simulations == 10000


def test_default_is_the_state_ce_sampler_and_paper_turns_every_improvement_off():
    c = ExperimentConfig.of()
    assert (c.adaptive.proposal_inputs, c.adaptive.proposal_window, c.weights_until_failure, c.adaptive.defensive) == (
        "state",
        True,
        True,
        0.2,
    )
    p = ExperimentConfig.of(**PRESETS["paper"])
    assert (
        p.adaptive.proposal_inputs,
        p.adaptive.proposal_window,
        p.weights_until_failure,
        p.adaptive.smoothing_at_failure,
    ) == (
        "gap",
        False,
        False,
        None,
    )
    assert (p.adaptive.elite_ties, p.adaptive.pretrain_cap, p.adaptive.defensive) == ("all", None, 0.0)


def test_authors_code_preset_is_the_paper_with_the_authors_training():
    c = ExperimentConfig.of(**PRESETS["authors-code"])
    assert (c.adaptive.smoothing, c.adaptive.ce_epochs, c.adaptive.weights, c.adaptive.final_estimate) == (
        0.5,
        1000,
        "recomputed",
        "last-stage",
    )
    assert c.adaptive.proposal_inputs == "gap" and c.adaptive.defensive == 0.0
    assert c.n_simulations == 100 + 10 * 100


@pytest.mark.parametrize(
    "field, value", [("fit", "sgd"), ("fit_max_steps", 0), ("fit_rows", 0), ("fit_tolerance", 0.0)]
)
def test_fitting_settings_are_validated(field, value):
    with pytest.raises(ConfigError, match=field):
        ExperimentConfig.of(**{field: value})


def test_paper_presets_keep_the_full_batch_adam_fit():
    for name in ("paper", "authors-code"):
        cfg = ExperimentConfig.of(**PRESETS[name])
        assert (cfg.adaptive.fit, cfg.adaptive.fit_rows, cfg.adaptive.fit_tolerance) == ("adam", None, None)


# -- one home per setting: SETTINGS, read by the config, the command line, the panel's form and the estimators ----

PAPER_RANGES = {
    # field: (lo, hi, lo_open, hi_open, whole): Innes & Ramamoorthy (2022) and the docstring of ExperimentConfig,
    # written here, not read from SETTINGS
    "smoothing": (0.0, 1.0, True, False, False),
    "quantile_level": (0.5, 1.0, False, True, False),
    "n_stages": (1, 1000, False, False, True),
    "n_per_stage": (2, math.inf, False, False, True),
    "n_final": (1, math.inf, False, False, True),
    "seed": (0, 2**64 - 1, False, False, True),
}


def inside(name: str, x: float) -> bool:
    lo, hi, lo_open, hi_open, whole = PAPER_RANGES[name]
    return (
        (not whole or float(x).is_integer()) and (x > lo if lo_open else x >= lo) and (x < hi if hi_open else x <= hi)
    )


def cli_error(argv: list[str]) -> str:
    """What ``pemviz run ARGV`` says of its settings before any work, in one line ("" when they are valid)."""
    from pemviz.cli import build_parser
    from pemviz.commands import setting_error
    from pemviz.commands.run import config_from_args

    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err):
            config_from_args(build_parser().parse_args(["run", *argv]))
    except SystemExit:  # argparse: a flag's text that is no number of the setting's kind
        return err.getvalue().strip().splitlines()[-1]
    except ConfigError as exc:
        return str(setting_error(exc))
    return ""


def test_every_setting_is_one_field_of_the_config_or_of_its_group_and_every_choice_is_explained():
    """At most 10 fields of the config's own besides its groups and the method's own settings
    (``method_settings``); a method's settings are a dataclass in the method's home, its group (splitting's) or its
    own (the adaptive and state methods': the cross-entropy sampler's, rows of the table, and the state method's
    besides); every setting one field of the config, of one group or of the sampler's settings, its owner's (the run's
    groups hold the run's)."""
    from pemviz.config import GROUP_OF, GROUPS
    from pemviz.methods import get_method
    from pemviz.methods.adaptive import CrossEntropySettings
    from pemviz.settings import CROSS_ENTROPY

    own = [f.name for f in dataclasses.fields(ExperimentConfig) if f.name != "method_settings"]
    assert len([name for name in own if name not in GROUPS]) <= 10 and set(GROUPS) <= set(own)
    fields = [name for name in own if name not in GROUPS] + list(GROUP_OF) + list(CROSS_ENTROPY)
    assert sorted(fields) == sorted(SETTINGS) and len(fields) == len(set(fields))
    assert "adaptive" not in GROUPS and get_method("adaptive").settings_class() is CrossEntropySettings
    assert GROUPS["ams"].__module__ == "pemviz.methods.ams"
    assert GROUPS["fallback"].__module__ == "pemviz.settings"  # any method's, below every method's folder
    state = get_method("state").settings_class()
    assert "state" not in GROUPS and state.__module__ == "pemviz.methods.state"
    assert issubclass(state, CrossEntropySettings)  # the sampler's settings and its own
    assert not {f.name for f in dataclasses.fields(state)} - set(CROSS_ENTROPY) & set(SETTINGS)  # its own: not rows
    defaults = ExperimentConfig.of()
    for name, s in SETTINGS.items():
        assert s.name == name and s.owner in (RUN, "adaptive", "ams", FALLBACK), name
        assert (name in CROSS_ENTROPY) == (s.owner == "adaptive"), name
        assert GROUP_OF.get(name) == s.owner if s.owner not in (RUN, "adaptive") else GROUP_OF.get(name) != "ams"
        assert s.accepts(defaults.value(name)), name  # the default is inside its own range
        if s.kind == "choice":
            assert [v for v, _ in s.choice_help] == list(s.choices), f"{name}: a hint for every choice, in order"


def test_help_texts_quote_no_measured_figures_and_no_markup():
    figures = re.compile(r"\d\.\d|\bmedian\b|\bmeasured\b|relative error|\bRMS\b|``|:(class|func|data):")
    for s in SETTINGS.values():
        for text in (s.help, *(what for _, what in s.choice_help)):
            assert not figures.search(text), f"{s.name}: {text!r}"


def test_alpha_means_the_same_in_the_docstring_the_flag_and_the_panel():
    from pemviz.app.form import FIELDS_BY_KEY
    from pemviz.cli import build_parser

    meaning = "the power on the importance weights in the CE loss"  # the paper's eq. 10 (not the update's weight)
    run = next(
        a
        for a in build_parser("run", full=False)._subparsers._group_actions[0].choices["run"]._actions
        if "--alpha" in a.option_strings
    )
    assert FIELDS_BY_KEY["smoothing"].hint == f"smoothing alpha, a number in (0, 1]: {meaning}"
    assert run.help == f"{FIELDS_BY_KEY['smoothing'].hint} (default 0.1)"
    from pemviz.methods.adaptive import CrossEntropySettings  # the settings' home documents them

    assert f"smoothing: alpha in (0, 1]: {meaning}." in " ".join(str(CrossEntropySettings.__doc__).split())
    assert "sigma in [0.5, 1): " + SETTINGS["quantile_level"].help in " ".join(
        str(CrossEntropySettings.__doc__).split()
    )


def test_every_flag_gives_the_hint_of_its_setting():
    from pemviz.cli import build_parser

    parser = build_parser()
    subparsers = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices
    seen = set()
    for command, p in subparsers.items():
        for action in p._actions:
            s = SETTINGS.get(action.dest)
            # estimate's --pem recomputes log p of logged rollouts, its --weights is another convention's choice
            if s is not None and (command, action.dest) not in {("estimate", "pem"), ("estimate", "weights")}:
                assert tuple(action.option_strings) == s.flags, (command, action.dest)
                assert action.help.replace("%%", "%").startswith(s.hint + " (default "), (command, action.dest)
                seen.add(action.dest)
    assert seen == {name for name, s in SETTINGS.items() if s.flags}  # every flag of SETTINGS is on a command


@settings(deadline=None)  # the first example imports the panel's form (seconds); the examples after it take ms
@given(
    name=st.sampled_from(list(PAPER_RANGES)),
    x=st.one_of(st.integers(-3, 2000), st.floats(-2, 3, allow_nan=False), st.sampled_from([0.0, 0.5, 1.0, 2**64])),
)
def test_a_value_is_refused_alike_by_config_form_and_command_line_with_the_same_allowed_words(name, x):
    from pemviz.app.form import FIELDS_BY_KEY, parse_number

    s = SETTINGS[name]
    value = int(x) if PAPER_RANGES[name][4] and float(x).is_integer() else x
    try:
        ExperimentConfig.of(**{name: value})
        config_error = ""
    except ConfigError as exc:
        config_error = str(exc)
    form_value, form_error = parse_number(FIELDS_BY_KEY[name], str(value))
    flag_error = cli_error([f"{s.flag}={value}"])
    if inside(name, float(x)):
        assert (config_error, form_error, flag_error, form_value) == ("", "", "", value)
    else:
        for error in (config_error, form_error, flag_error):
            assert error.endswith(f"{s.words} must be {s.allowed}"), (error, s.allowed)
        assert flag_error.startswith((f"{s.flag}: {s.title} = ", f"pemviz run: error: argument {s.flag}"))


def test_each_estimator_reads_its_own_settings_and_the_run_level_ones_only():
    import pemviz.estimators.ams as ams
    import pemviz.estimators.cross_entropy as ce
    import pemviz.estimators.fallback as fallback
    import pemviz.estimators.state as state
    import pemviz.methods.adaptive as adaptive
    from pemviz.estimators.ams import AdaptiveMultilevelSplitting
    from pemviz.estimators.cross_entropy import CrossEntropy
    from pemviz.estimators.fallback import PlainFallback
    from pemviz.estimators.state import StateCrossEntropy
    from pemviz.methods.state import StateSettings
    from pemviz.settings import FallbackSettings

    own = {f.name for f in dataclasses.fields(StateSettings)} - set(settings_of("adaptive"))  # the state method's own
    fields = set(SETTINGS) | own | {"has_final_batch", "n_simulations"}
    # what runs after any method's stages (a Method's ``then``) reads the fallback's settings, whose retry's N and
    # plain Monte Carlo's cap the settings' module gives, and no method's
    for modules, cls, owner in (
        ((ce, adaptive), CrossEntropy, "adaptive"),
        ((ams,), AdaptiveMultilevelSplitting, "ams"),
        ((ce, adaptive, state), StateCrossEntropy, "state"),  # the cross-entropy sampler's and its own
        ((fallback,), PlainFallback, FALLBACK),
    ):
        source = "".join(open(str(module.__file__)).read() for module in modules)
        read = set(
            re.findall(
                r"\b(?:cfg|config|ce|own)(?:\.adaptive|\.ams|\.fallback|\.stop|\.execution|\.perception)?\.([a-z_]+)\b",
                source,
            )
        )
        if cls is PlainFallback:  # the fallback's settings' own methods read them too (the retry's N)
            read |= set(re.findall(r"\bself\.([a-z_]+)\b", inspect.getsource(FallbackSettings)))
        read &= fields
        read -= {"has_final_batch", "n_simulations"}
        assert cls.SETTINGS, owner  # an estimator that owns nothing would pass the two checks below vacuously
        assert read <= set(cls.SETTINGS) | set(settings_of(RUN)), (
            owner,
            read - set(cls.SETTINGS) - set(settings_of(RUN)),
        )
        assert set(cls.SETTINGS) <= read, (owner, set(cls.SETTINGS) - read)  # no setting claimed and never read
    assert not set(settings_of("adaptive")) & set(settings_of("ams")) and not own & set(settings_of("adaptive"))
    assert not set(settings_of(FALLBACK)) & set(settings_of("adaptive"))
    # every setting is read by the run or by one of the estimators checked above: an owner misspelt in SETTINGS
    # (or a method's settings without an estimator reading them) would leave its settings read by nobody
    assert {s.owner for s in SETTINGS.values()} == {RUN, "adaptive", "ams", FALLBACK}


def test_the_state_methods_settings_are_its_own_and_recorded_where_runs_always_recorded_them():
    """The state method's settings are its record's (``Method.settings``), held as ``method_settings``; every run
    records them after splitting's, a state run its own values; a recorded config makes the same config again; given
    to another method they are refused in one line (the config's and the flag's)."""
    from pemviz.methods import get_method
    from pemviz.methods.adaptive import CrossEntropySettings
    from pemviz.methods.state import StateSettings

    cfg = ExperimentConfig.of(method="state", state_share=0.3, state_model="network")
    assert get_method("state").settings_class() is StateSettings and not hasattr(cfg, "state")
    assert cfg.method_settings == StateSettings(state_share=0.3, state_model="network", state_fit_errors=False)
    assert (cfg.value("state_share"), cfg.replace(state_fit_errors=True).method_settings.state_fit_errors) == (
        0.3,
        True,
    )
    keys = list(ExperimentConfig.of().flat())
    assert keys[-5:] == ["ams_score", "ams_replicas", "state_share", "state_model", "state_fit_errors"]
    assert list(cfg.flat()) == keys
    assert [cfg.flat()[k] for k in keys[-3:]] == [0.3, "network", False]
    assert [ExperimentConfig.of(method=m).flat()[k] for m in ("mc", "ams") for k in keys[-3:]] == [
        0.1,
        "glm",
        False,
    ] * 2
    assert (
        ExperimentConfig.of(**cfg.flat()) == cfg
        and ExperimentConfig.of(**ExperimentConfig.of().flat()).method_settings == CrossEntropySettings()
    )
    # to the adaptive method and back: the cross-entropy sampler's settings carry over, the state method's own do not
    changed = cfg.replace(n_stages=4).replace(method="adaptive")
    assert type(changed.method_settings) is CrossEntropySettings and changed.adaptive.n_stages == 4
    assert changed.replace(method="state").method_settings == StateSettings(n_stages=4)
    with pytest.raises(ConfigError, match=r"^state_share is a setting of method state: give it with method = 'state'$"):
        ExperimentConfig.of(state_share=0.3)
    with pytest.raises(ConfigError, match=r"^state_share = 0.95 is invalid: state_share \+ plain_share must be <= 1$"):
        ExperimentConfig.of(method="state", state_share=0.95, plain_share=0.1)
    assert (
        cli_error(["--state-share", "0.3"]) == "--state-share is a setting of method state: give it with --method state"
    )
    assert cli_error(["--method", "state", "--state-share", "1"]).endswith(
        "the PEM's share of the state proposal's mixture must be a number in (0, 1)"
    )


def test_an_estimator_gives_its_own_settings_with_the_values_it_was_built_with():
    from pemviz.estimators.ams import AdaptiveMultilevelSplitting
    from pemviz.estimators.cross_entropy import CrossEntropy
    from pemviz.scenarios.toy import ToyParams
    from pemviz.scenarios.toy.problem import toy_problem

    problem = toy_problem(ToyParams(10, 5, 3, 0.9))
    config = ExperimentConfig.of(smoothing=0.3, n_stages=4, quantile_level=0.9, n_final=500)
    ce = CrossEntropy(config, problem).get_params()
    assert (ce["smoothing"], ce["n_stages"], ce["quantile_level"], ce["n_final"]) == (0.3, 4, 0.9, 500)
    # the params rebuild the config they came from (scikit-learn's clone): each value the config's, and the fields
    # left out are the run-level ones, at their defaults here
    assert ExperimentConfig.of(**ce) == config
    assert "seed" not in ce and "ams_killed" not in ce  # run-level, and another estimator's
    cfg = ExperimentConfig.of(method="ams", n_per_stage=40, ams_killed=7)
    assert AdaptiveMultilevelSplitting(cfg, problem).get_params() == {
        "ams_killed": 7,
        "ams_max_iterations": 10_000,
        "ams_score": "robustness",
        "ams_replicas": 1,
    }


def test_an_optional_number_s_messages_say_what_to_type_and_none_is_typed_as_such() -> None:
    """`--rel-error abc` says to type ``none or a number in (0, 10]`` (was ``None or ...``, a Python word), and
    ``none`` typed on the command line or in the panel's field is the setting's None."""
    from pemviz.app.form import FIELDS_BY_KEY, parse_number
    from pemviz.cli import build_parser
    from pemviz.settings import SETTINGS

    rel = SETTINGS["rel_error"]
    with pytest.raises(ValueError) as refused:
        rel.parse("abc")
    assert str(refused.value) == "'abc' is not a number; type none or a number in (0, 10] (the target relative error)"
    assert rel.parse(" None ") is None and rel.parse("0.05") == 0.05
    with pytest.raises(ValueError, match="'none' is not a number; type a whole number >= 2"):
        SETTINGS["n_per_stage"].parse("none")  # not optional: none is no value of it
    assert build_parser().parse_args(["run", "--rel-error", "none"]).rel_error is None
    assert parse_number(FIELDS_BY_KEY["rel_error"], "none") == (None, "")


def test_the_fallbacks_settings_are_a_group_of_their_own_read_whatever_the_method():
    """The retry and plain Monte Carlo after the stages have their own settings (``config.fallback``), given by their
    flat names to any method whose record names a ``then`` (the adaptive and state methods), checked in one line, and
    no longer fields of the cross-entropy sampler's settings; the retry's N is theirs."""
    from pemviz.methods import records
    from pemviz.methods.adaptive import CrossEntropySettings
    from pemviz.methods.state import StateSettings
    from pemviz.settings import RETRY_MOST_N, FallbackSettings

    assert [r.name for r in records() if r.then] == ["adaptive", "state"]
    cfg = ExperimentConfig.of(method="state", plain_fallback=7, retry_factor=3)
    assert cfg.fallback == FallbackSettings(plain_fallback=7, retry_factor=3) and cfg.value("retry_factor") == 3
    assert cfg.adaptive == StateSettings() and not {"plain_fallback", "retry_factor"} & {
        f.name for f in dataclasses.fields(CrossEntropySettings)
    }
    # N x retry_factor, capped at 10,000; none with a stop rule, a factor below 2, no plain fallback or N at the cap
    assert (cfg.fallback.retry_n(100), cfg.fallback.retry_n(4_000), cfg.fallback.retry_n(100, "rel_error")) == (
        300,
        RETRY_MOST_N,
        None,
    )
    assert (
        FallbackSettings(retry_factor=1).retry_n(100) is None
        and FallbackSettings(plain_fallback=0).retry_n(100) is None
    )
    assert FallbackSettings().retry_n(RETRY_MOST_N) is None
    with pytest.raises(ConfigError, match=r"^retry_factor = -1 is invalid: the retry's factor on N must be a whole"):
        ExperimentConfig.of(method="state", retry_factor=-1)
