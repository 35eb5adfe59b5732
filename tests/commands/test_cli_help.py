"""Every help text of the ``pemviz`` command line is plain text a user can act on."""

from __future__ import annotations

import argparse
import re

import pytest
from pemviz.cli import build_parser


def all_parsers() -> list[tuple[str, argparse.ArgumentParser]]:
    """(command path, parser) for ``pemviz`` and every sub-command, depth first."""
    out = []

    def walk(name: str, parser: argparse.ArgumentParser) -> None:
        out.append((name, parser))
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for sub, p in action.choices.items():
                    walk(f"{name} {sub}", p)

    walk("pemviz", build_parser())
    return out


MARKUP = re.compile(r"``|:(func|class|data|mod|meth):|spec section|\bissue \d|\bDEFAULT_[A-Z_]+|pemviz\.pem\.[A-Z]")


@pytest.mark.parametrize(("name", "parser"), all_parsers(), ids=[n for n, _ in all_parsers()])
def test_help_has_no_markup_no_internal_names_and_no_documents_the_user_lacks(name, parser) -> None:
    text = parser.format_help()
    assert not MARKUP.search(text), f"{name} --help: {MARKUP.search(text).group(0)!r}"


def test_run_help_gives_the_real_pem_default() -> None:
    from pemviz.commands import SHOWN_DEFAULTS
    from pemviz.pem.recipes import DEFAULT_PEM_NAME

    run = dict(all_parsers())["pemviz run"]
    assert SHOWN_DEFAULTS["pem"] == DEFAULT_PEM_NAME == "ml-nn"
    assert f"(default {DEFAULT_PEM_NAME})" in " ".join(run.format_help().split())


def test_run_help_gives_the_engines_real_chunks() -> None:
    from pemviz.commands import SHOWN_DEFAULTS
    from pemviz.core.lockstep import DEFAULT_CHUNK_SIZE
    from pemviz.engine.experiment import STREAM_ABOVE

    run = " ".join(dict(all_parsers())["pemviz run"].format_help().split())
    assert SHOWN_DEFAULTS["chunk_rollouts"] == (
        f"{DEFAULT_CHUNK_SIZE}, and only stages above {STREAM_ABOVE} " "rollouts stream"
    )
    assert f"(default {DEFAULT_CHUNK_SIZE}, and only stages above {STREAM_ABOVE} rollouts stream)" in run


def test_every_command_that_takes_a_preset_accepts_quick() -> None:
    from pemviz.commands import split_choices
    from pemviz.commands.run import config_from_args
    from pemviz.presets import PRESETS

    parser = build_parser()
    quick = config_from_args(parser.parse_args(["run", "--preset", "quick"]))
    # the quick preset as its documentation gives it (not read back from PRESETS), none of it the default's
    assert (
        quick.adaptive.n_stages,
        quick.adaptive.ce_epochs,
        quick.adaptive.pretrain_rollouts,
        quick.adaptive.pretrain_epochs,
        quick.adaptive.learning_rate,
    ) == (
        8,
        200,
        50,
        200,
        2e-2,
    )
    assert (quick.adaptive.smoothing, quick.n_per_stage) == (0.1, 100)  # what it leaves: the default sampler's
    overridden = config_from_args(parser.parse_args(["run", "--preset", "quick", "--k", "3"]))
    assert (overridden.adaptive.n_stages, overridden.adaptive.ce_epochs) == (
        3,
        200,
    )  # a flag given overrides the preset, only there
    assert split_choices("quick,paper", PRESETS, "presets") == ("quick", "paper")  # validate --presets, tables --extra
    assert parser.parse_args(["serve", "--preset", "quick"]).preset == "quick"
    for name in ("pemviz run", "pemviz serve", "pemviz validate", "pemviz tables"):
        assert "quick" in " ".join(dict(all_parsers())[name].format_help().split()), name


HEAVY = (
    "torch",
    "pemviz.engine.experiment",
    "pemviz.estimators.base",
    "pemviz.core.problems",
    "pemviz.scenarios.problems",
)
"""What a help page must not load (the estimators' package itself is light: its registry of methods, which a config's
checks read)."""


def modules_loaded_by(argv: list[str], heavy: tuple[str, ...] = HEAVY, cwd: str | None = None) -> set[str]:
    """The modules of ``heavy`` that ``pemviz ARGV`` has imported by the time it exits, in a new process."""
    import subprocess
    import sys

    code = (
        "import contextlib, io, sys\nfrom pemviz.cli import main\n"
        "with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):\n"
        f"    try:\n        main({argv!r})\n    except SystemExit:\n        pass\n"
        f"print(' '.join(m for m in {heavy!r} if m in sys.modules))"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True, cwd=cwd
    )
    return set(proc.stdout.split())


@pytest.mark.parametrize("argv", [["--help"], ["run", "--help"], ["serve", "--help"], ["data", "--help"]])
def test_help_imports_no_torch_and_no_engine(argv) -> None:
    assert modules_loaded_by(argv) == set()


def test_a_braking_run_imports_no_scipy_stats(tmp_path) -> None:
    """scipy.stats takes ~0.5 s to import: a braking run (no measurement errors) must not pay it, while a run does
    load the engine (so the check sees a real run)."""
    loaded = modules_loaded_by(
        ["run", "--preset", "quick", "--no-record"], ("pemviz.engine.experiment", "scipy.stats"), cwd=str(tmp_path)
    )
    assert loaded == {"pemviz.engine.experiment"}


def test_the_lean_parser_lists_every_command_with_the_help_of_its_own_parser() -> None:
    from pemviz.commands import COMMANDS

    full, lean = build_parser(), build_parser("run", full=False)
    helps = [{a.dest: a.help for a in p._subparsers._group_actions[0]._choices_actions} for p in (full, lean)]
    assert helps[0] == helps[1] and set(helps[0]) == set(COMMANDS)
    assert lean.parse_args(["run", "--sigma", "0.9"]).quantile_level == 0.9  # run's own parser, whole
    with pytest.raises(SystemExit):  # the others are listed only
        lean.parse_args(["validate", "--seeds", "3"])


SHIPPED_PEM_ARGS = {
    "run": ["run", "--no-record"],
    "validate": ["validate", "--problems", "toy-1e-3", "--seeds", "1", "--out", "o"],
    "tables": ["tables", "--problem", "toy-1e-3", "--out", "o"],
    "estimate": ["estimate", "rollouts.parquet", "--no-record"],
    "serve": ["serve"],
}
"""Each command that takes ``--pem``, with the rest of a command line it would run."""


@pytest.mark.parametrize("command", list(SHIPPED_PEM_ARGS))
def test_every_command_refuses_an_unknown_pem_with_the_same_message_naming_the_shipped_ones(
    command, tmp_path, monkeypatch, capsys
):
    from pemviz.cli import main
    from pemviz.pem.store import assets_dir

    monkeypatch.chdir(tmp_path)  # nothing may be written here
    assert main([*SHIPPED_PEM_ARGS[command], "--pem", "no-such-pem"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (
        f"pemviz {command}: error: --pem no-such-pem: neither a PEM file nor one of the shipped PEMs "
        f"(gbt, ml-nn, in {assets_dir()})"
    ), err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("command", list(SHIPPED_PEM_ARGS))
def test_every_command_takes_a_shipped_pem_by_name(command) -> None:
    from pemviz.commands import pem_argument

    args = build_parser().parse_args([*SHIPPED_PEM_ARGS[command], "--pem", "gbt"])
    assert args.pem == "gbt" and pem_argument(args.pem) == "gbt"


def test_help_lists_every_registered_scenario_from_the_registry(monkeypatch) -> None:
    """``pemviz --help`` and ``pemviz run --help`` name each scenario the registry holds (a scenario registered now
    included) and, in run's, what each simulates: the registry's description up to its first ``;``."""
    import contextlib
    import io

    from pemviz.cli import main
    from pemviz.scenarios.registry import Scenario, register, registered, unregister

    register(Scenario("help-probe", "a probe scene for the help; failure: none", None, "pemviz.scenarios.builtin:toy"))
    try:
        names = registered()
        assert {"braking", "cut-in", "cut-in-rare", "toy", "crowd", "crossing", "help-probe"} <= set(names)
        pages = {}
        for argv in (["--help"], ["run", "--help"]):
            out = io.StringIO()
            with contextlib.redirect_stdout(out), pytest.raises(SystemExit):
                main(argv)
            pages[argv[0]] = " ".join(out.getvalue().split())
        assert f"record the run (scenarios: {', '.join(names)})" in pages["--help"]
        run = pages["run"]
        assert f"scenario, one of {', '.join(names)}: what is simulated" in run
        assert "; help-probe: a probe scene for the help" in run and "failure: none" not in run
        assert "braking: automated braking behind a lead car, the PEM as the camera's detector (exact answer);" in run
    finally:
        unregister("help-probe")
    assert "help-probe" not in " ".join(build_parser().format_help().split())


def test_python_dash_m_pemviz_is_the_program(tmp_path) -> None:
    import subprocess
    import sys

    import pemviz
    from pemviz.scenarios.registry import registered

    version = subprocess.run(
        [sys.executable, "-m", "pemviz", "--version"], cwd=tmp_path, capture_output=True, text=True, timeout=120
    )
    assert version.returncode == 0 and pemviz.__version__ in version.stdout, version.stderr
    bad = subprocess.run(
        [sys.executable, "-m", "pemviz", "run", "--scenario", "nosuch"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert bad.returncode == 2 and "Traceback" not in bad.stderr
    assert bad.stderr.strip().splitlines() == [
        "pemviz run: error: --scenario: scenario = 'nosuch' is invalid: use one of " + ", ".join(registered())
    ]
