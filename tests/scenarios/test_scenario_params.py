"""Scenario parameters a user can set (``pemviz run --param NAME=VALUE``): the schema derived from the scenario's
dataclass, the command line's parsing and its one-line refusals, the config that carries them into the problem and
the files, and the kept answers that hold for the default scene only."""

from __future__ import annotations

import dataclasses
import json
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pemviz.config import ConfigError, ExperimentConfig
from pemviz.scenarios.braking.simulator import BrakingParams
from pemviz.scenarios.cut_in.scenario import RARITY_SETTINGS, CutInParams
from pemviz.scenarios.parameters import (
    Parameter,
    ParameterError,
    apply_parameters,
    as_pairs,
    parse_assignment,
    scenario_parameters,
)
from pemviz.settings import SCENARIOS

from conftest import REPO

SMALL = ["--no-record", "--k", "1", "--n", "50", "--n-final", "50"]


def by_name(scenario: str) -> dict:
    return {p.name: p for p in scenario_parameters(scenario)}


# -- the schema ---------------------------------------------------------------------------------------------------


def test_the_schema_is_the_dataclass_s_scalar_fields_with_the_scenario_s_defaults_and_units():
    cut_in = by_name("cut-in")
    gap = cut_in["cut_in_gap_m"]
    assert (gap.kind, gap.unit, gap.default) == ("float", "m", CutInParams().cut_in_gap_m)
    assert by_name("cut-in-rare")["cut_in_gap_m"].default == RARITY_SETTINGS["rare"]["cut_in_gap_m"]
    units = (cut_in["cut_in_speed_mps"].unit, cut_in["dt_s"].unit, cut_in["ego_a_min_mps2"].unit)
    assert units == ("m/s", "s", "m/s^2")
    assert (cut_in["n_objects"].kind, cut_in["n_objects"].default) == ("int", 5)
    assert "traffic" not in cut_in and "idm" not in cut_in and "tracker" not in cut_in  # not scalars
    braking = by_name("braking")
    assert braking["latched_brake"].kind == "bool" and braking["gap0_m"].default == BrakingParams().gap0_m
    assert "lead_speed_profile_mps" not in braking and "brake_decel_mps2" not in braking
    for scenario in SCENARIOS:  # every parameter's default is the scenario's own dataclass's value
        for p in scenario_parameters(scenario):
            assert apply_parameters(scenario, {p.name: p.default}) == apply_parameters(scenario, {}), p.name


def test_the_dataclass_s_own_check_is_the_range():
    assert apply_parameters("cut-in", {"cut_in_gap_m": 19.5}).cut_in_gap_m == 19.5
    with pytest.raises(ParameterError, match=r"cut_in_gap_m must be finite and >= 0, got -1.0"):
        apply_parameters("cut-in", {"cut_in_gap_m": -1.0})
    with pytest.raises(ParameterError, match=r"n_objects must be an integer in 3\.\.6"):
        apply_parameters("cut-in", {"n_objects": 9})
    with pytest.raises(ParameterError, match=r"^the braking scenario: dt_s must be finite and > 0, got 0.0$"):
        apply_parameters("braking", {"dt_s": 0.0})
    for scenario, values, words in (  # the scenario a user named, never the dataclass's class name
        ("toy", {"braking": -1}, "the toy scenario: need 1 <= safe <= braking < total, got total=100, braking=-1"),
        ("crossing", {"walk_speed_mps": -1.0}, "the crossing scenario: walk_speed_mps must be in [0.3, 4], got -1.0"),
        ("cut-in", {"cut_in_gap_m": -1.0}, "the cut-in scenario: cut_in_gap_m must be finite and >= 0, got -1.0"),
    ):
        with pytest.raises(ParameterError) as refused:
            apply_parameters(scenario, values)
        assert str(refused.value).startswith(words) and "Params" not in str(refused.value)
    with pytest.raises(ParameterError, match="use one of dt_s, n_steps, gap0_m"):
        apply_parameters("braking", {"cut_in_gap_m": 19.5})
    with pytest.raises(ParameterError, match="is not a whole number"):
        apply_parameters("cut-in", {"n_objects": 4.0})


# -- the config ---------------------------------------------------------------------------------------------------


def test_the_config_checks_the_pairs_against_the_scenario():
    cfg = ExperimentConfig.of(scenario="cut-in", scenario_params=(("cut_in_gap_m", 19.5),))
    assert cfg.scenario_params == (("cut_in_gap_m", 19.5),)
    for bad in (
        (("cut_in_gap_m", 19.5),),
        (("gap0_m", -1.0),),
        (("gap0_m", 12.0), ("gap0_m", 13.0)),
        ((("gap0_m",),)),
        [("gap0_m", 12.0)],
    ):
        with pytest.raises(ConfigError) as info:
            ExperimentConfig.of(scenario_params=bad)
        assert info.value.field == "scenario_params" and "\n" not in str(info.value), bad
    with pytest.raises(ConfigError, match="give it once") as info:
        ExperimentConfig.of(margin=1.0, scenario_params=(("crash_gap_m", 1.0),))
    assert info.value.field == "margin"


def test_a_json_document_s_pairs_make_the_same_config():
    cfg = ExperimentConfig.of(scenario="cut-in", scenario_params=(("cut_in_gap_m", 19.5), ("n_objects", 4)))
    recorded = json.loads(json.dumps(cfg.flat()))["scenario_params"]
    assert ExperimentConfig.of(scenario="cut-in", scenario_params=as_pairs(recorded)) == cfg


# -- the problem and its kept answers -----------------------------------------------------------------------------


def test_the_problem_has_the_gap_and_no_reference_of_the_default_scene():
    from pemviz.scenarios.problems import problem_for

    default = problem_for(ExperimentConfig.of(scenario="cut-in"))
    moved = problem_for(ExperimentConfig.of(scenario="cut-in", scenario_params=(("cut_in_gap_m", 19.5),)))
    assert "cutting in 20 m ahead" in default.description and default.reference is not None
    assert "cutting in 19.5 m ahead" in moved.description and moved.reference is None
    same = problem_for(ExperimentConfig.of(scenario="cut-in", scenario_params=(("cut_in_gap_m", 20.0),)))
    assert same.reference == default.reference  # the default's own value: the same scene, the same reference
    assert problem_for(ExperimentConfig.of(scenario="cut-in", scenario_params=(("n_objects", 4),))).n_objects == 4


def test_the_braking_exact_answer_is_dropped_or_recomputed_for_changed_parameters():
    from pemviz.pem import load_pem
    from pemviz.scenarios.braking.truth_latched import latched_log_failure_probability
    from pemviz.scenarios.problems import problem_for

    default = problem_for(ExperimentConfig.of(pem_shift=0.5))
    assert default.exact_log_p is not None and default.severity_exact
    assert default.alternatives[0].exact_log_p is not None
    moved = problem_for(ExperimentConfig.of(pem_shift=0.5, scenario_params=(("gap0_m", 12.0),)))
    assert moved.exact_log_p is None and not moved.severity_exact  # kept for the default scene only
    assert moved.alternatives[0].exact_log_p is None
    assert moved.drawing.params == dataclasses.replace(BrakingParams(), gap0_m=12.0)
    margin = problem_for(ExperimentConfig.of(margin=1.5))
    param = problem_for(ExperimentConfig.of(scenario_params=(("crash_gap_m", 1.5),)))
    assert param.exact_log_p == margin.exact_log_p is not None and param.drawing == margin.drawing
    latched = problem_for(ExperimentConfig.of(scenario_params=(("latched_brake", True), ("gap0_m", 12.0))))
    truth = latched_log_failure_probability(
        load_pem(None).logit_at_gap, BrakingParams(latched_brake=True, gap0_m=12.0)
    ).log_p_fail
    assert latched.exact_log_p == truth and math.isfinite(truth)
    unmoved = latched_log_failure_probability(load_pem(None).logit_at_gap, BrakingParams(latched_brake=True))
    assert truth != unmoved.log_p_fail  # recomputed for the gap given, not the default scene's


# -- the command line ---------------------------------------------------------------------------------------------


def run(argv: list[str], capsys) -> tuple[int, str, str]:
    from pemviz.cli import main

    code = main(["run", *argv])
    out = capsys.readouterr()
    return code, out.out, out.err


def test_a_run_with_a_parameter_prints_and_records_it(tmp_path, capsys):
    result, rollouts = tmp_path / "result.json", tmp_path / "rollouts.parquet"
    code, out, err = run(
        [
            "--scenario",
            "cut-in",
            "--param",
            "cut_in_gap_m=19.5",
            *SMALL,
            "--json",
            str(result),
            "--save-rollouts",
            str(rollouts),
        ],
        capsys,
    )
    assert code == 0, err
    header = out.splitlines()[0]
    assert header.startswith("pemviz: tilt on the cut-in scenario (cut_in_gap_m=19.5 m), spec "), header
    assert "reference" not in out  # the moderate setting's reference is for its own scene
    doc = json.loads(result.read_text())
    assert doc["settings"]["scenario_params"] == [["cut_in_gap_m", 19.5]]
    assert doc["reference"] is None and doc["exact"] is None
    assert "cutting in 19.5 m ahead" in doc["problem"]["description"]
    from pemviz.commands.estimate import known_answer, run_problem
    from pemviz.io.rollout_format import sidecar_path
    from pemviz.io.rollouts import read_rollouts

    sidecar = json.loads(sidecar_path(rollouts).read_text())
    assert sidecar["provenance"]["config"]["scenario_params"] == [["cut_in_gap_m", 19.5]]
    # no reference of another scene
    assert known_answer(run_problem(read_rollouts(rollouts), "crash", True)) == (None, None)


def test_a_parameter_at_its_default_is_not_named_in_the_header(capsys):
    code, out, err = run(["--scenario", "cut-in", "--param", "cut_in_gap_m=20", *SMALL], capsys)
    assert code == 0, err
    assert out.splitlines()[0].startswith("pemviz: tilt on the cut-in scenario, spec "), out.splitlines()[0]


@pytest.mark.parametrize(
    "param, words",
    [
        ("cut_in_gapm=19.5", "'cut_in_gapm' is not a parameter of the cut-in scenario; use one of dt_s, n_steps, "),
        ("cut_in_gap_m=-3", "the cut-in scenario: cut_in_gap_m must be finite and >= 0, got -3.0"),
        ("cut_in_gap_m=abc", "cut_in_gap_m='abc' is not a number: cut_in_gap_m takes a number in m (default 20.0)"),
        ("cut_in_gap_m", "'cut_in_gap_m' is not NAME=VALUE; the cut-in scenario's names: dt_s, "),
        ("n_objects=4.5", "n_objects='4.5' is not a whole number"),
    ],
)
def test_a_bad_name_or_value_is_one_line_exit_2_and_nothing_written(param, words, tmp_path, capsys):
    result = tmp_path / "r.json"
    code, out, err = run(["--scenario", "cut-in", "--param", param, *SMALL, "--json", str(result)], capsys)
    assert code == 2 and out == ""
    assert len(err.splitlines()) == 1 and err.startswith("pemviz run: error: --param: "), err
    assert words in err, err
    assert "cut_in_gap_m, " in err or param.partition("=")[0] in err  # the allowed names, or the field and its range
    assert list(tmp_path.iterdir()) == []


def test_the_flag_s_help_is_the_setting_s():
    from pemviz.cli import build_parser

    help_text = " ".join(
        build_parser("run", full=False)._subparsers._group_actions[0].choices["run"].format_help().split()
    )
    assert "--param NAME=VALUE" in help_text and "cut_in_gap_m=25" in help_text


PARSE_NAMES = sorted({p.name for s in SCENARIOS for p in scenario_parameters(s)} | {"", "x", "cut_in_gap"})


@settings(max_examples=300, deadline=None)
@given(
    scenario=st.sampled_from(SCENARIOS),
    text=st.one_of(
        st.text(),
        st.builds(
            lambda n, v: f"{n}={v}",
            st.sampled_from(PARSE_NAMES),
            st.one_of(
                st.text(),
                st.floats().map(repr),
                st.integers().map(str),
                st.sampled_from(["true", "no", "1e400", "nan", " 3 ", "1_0"]),
            ),
        ),
    ),
)
def test_any_text_is_a_pair_of_the_scenario_or_one_line_saying_what_is_wrong(scenario, text):
    params = by_name(scenario)
    try:
        name, value = parse_assignment(scenario, text)
    except ParameterError as exc:
        message = str(exc)
        assert message and "\n" not in message and "\r" not in message
        return
    p = params[name]
    assert p.check(value) == value and type(value).__name__ == p.kind
    assert not isinstance(value, float) or math.isfinite(value)


@settings(max_examples=40, deadline=None)
@given(text=st.text(max_size=30))
def test_the_command_line_refuses_any_bad_param_text_with_one_config_error(text):
    from pemviz.cli import build_parser
    from pemviz.commands import setting_error
    from pemviz.commands.run import config_from_args

    args = build_parser("run", full=False).parse_args(["run", "--scenario", "cut-in", f"--param={text}"])
    try:
        cfg = config_from_args(args)
    except ConfigError as exc:
        line = str(setting_error(exc))
        assert line.startswith("--param: ") and "\n" not in line
        return
    assert len(cfg.scenario_params) == 1


# -- the docs -----------------------------------------------------------------------------------------------------


def parameter_table() -> str:
    """The Markdown table of every scenario's parameters (the user guide's, ``docs/cli.md``): one row per name, its
    kind and unit, and its default in each scenario (``-``: not one of its)."""
    rows: dict[str, dict[str, Parameter]] = {}
    for scenario in SCENARIOS:
        for p in scenario_parameters(scenario):
            rows.setdefault(p.name, {})[scenario] = p
    head = "| parameter | type | unit | " + " | ".join(SCENARIOS) + " |"
    lines = [head, "|---|---|---|" + "---:|" * len(SCENARIOS)]
    for name, by in rows.items():
        first = next(iter(by.values()))
        cells = [f"`{by[s].default!r}`" if s in by else "-" for s in SCENARIOS]
        lines.append(f"| `{name}` | {first.kind} | {first.unit or '-'} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def test_the_user_guide_s_table_is_the_schema():
    text = (REPO / "docs" / "cli.md").read_text()
    start, end = "<!-- scenario-params -->\n", "\n<!-- /scenario-params -->"
    assert text[text.index(start) + len(start) : text.index(end)] == parameter_table()
    assert "--param" in (REPO / "docs" / "cut-in.md").read_text()
