"""A method of one's own, registered from a module as the guide says (:mod:`tests.estimators.user_method`), runs
wherever a built-in one does: ``pemviz run --method``, its rollout file and recording, ``pemviz estimate``,
``pemviz validate`` and ``pemviz.testing.check_estimator`` (by name or as a ``Method`` object); a bad plugin or name is
one line."""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
from pemviz.config import ConfigError, ExperimentConfig
from pemviz.estimators import build_estimator, run_plan
from pemviz.estimators.fixed import FixedSampler
from pemviz.methods import (
    Method,
    get_method,
    method_names,
    register_method,
    registered_name,
    unregister_method,
)
from pemviz.testing import check_estimator

HERE = Path(__file__).resolve().parent


@pytest.fixture
def defensive():
    from . import user_method

    register_method(user_method.METHOD, replace=True)
    yield user_method.METHOD
    unregister_method("defensive-mc")


def _pemviz(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    path = os.pathsep.join(p for p in (str(HERE), os.environ.get("PYTHONPATH")) if p)  # this pemviz, if set
    env = {**os.environ, "PEMVIZ_METHODS": "user_method", "PYTHONPATH": path}
    return subprocess.run(
        [sys.executable, "-m", "pemviz.cli", *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=600
    )


def test_the_built_in_methods_are_registered_records():
    assert method_names()[:7] == ("adaptive", "mc", "naive50", "mixed50", "ams", "tilt", "state")
    assert not get_method("ams").weighted and not get_method("ams").extensible
    assert all(get_method(m).weighted for m in ("adaptive", "mc", "naive50", "mixed50", "tilt"))
    with pytest.raises(ValueError, match="built in"):
        register_method(Method("mc", "mine", "x:y"))
    with pytest.raises(ValueError, match="built in and stays"):
        unregister_method("adaptive")
    with pytest.raises(ValueError, match="check_estimator: unknown method 'nope'; use one of adaptive, mc"):
        registered_name("nope", "check_estimator")


def test_a_registered_method_is_a_config_method_and_builds(defensive):
    assert "defensive-mc" in method_names()
    cfg = ExperimentConfig.of(method="defensive-mc", scenario="braking", n_per_stage=500)
    assert run_plan(cfg).stages[-1].n_rollouts == 500
    from pemviz.scenarios.problems import build_problem

    est = build_estimator(cfg, build_problem("toy-1e-3"))
    assert isinstance(est, FixedSampler) and est.sampler.eps == 0.3
    unregister_method("defensive-mc")
    with pytest.raises(ConfigError, match="method = 'defensive-mc' is invalid: use one of adaptive, mc, naive50"):
        ExperimentConfig.of(method="defensive-mc")
    register_method(defensive)


def test_check_estimator_takes_a_registered_name_and_a_method_object(defensive, tmp_path):
    report = check_estimator("defensive-mc", folder=tmp_path / "a")
    assert {"interface", "unbiased", "verdicts", "rollout-file", "recording"} <= set(report.passed)
    unregister_method("defensive-mc")
    report = check_estimator(defensive, folder=tmp_path / "b")  # the object itself: registered by the check
    assert "unbiased" in report.passed and "defensive-mc" in method_names()

    def biased(config, problem, check=None):  # the same sampler, its estimate doubled: caught
        est = defensive.builder()(config, problem, check)
        result = est.result

        def doubled():
            mu, used = result()
            return dataclasses.replace(mu, log_mu_hat=mu.log_mu_hat + math.log(2.0)), used

        est.result = doubled
        return est

    from pemviz.testing import ConformanceError

    with pytest.raises(ConformanceError, match=r"check_estimator\('doubled'\): (unbiased|rollout-file): "):
        check_estimator(
            Method("doubled", "defensive-mc, every weight doubled", biased, settings=defensive.settings),
            folder=tmp_path / "c",
        )
    unregister_method("doubled")


def test_pemviz_run_records_and_re_estimates_a_method_of_ones_own(tmp_path):
    proc = _pemviz(
        "run",
        "--scenario",
        "toy",
        "--param",
        "total=10",
        "--param",
        "braking=5",
        "--param",
        "safe=3",
        "--method",
        "defensive-mc",
        "--coin-share",
        "0.2",
        "--coin-radius",
        "4",
        "--n",
        "3000",
        "--seed",
        "2",
        "--save-rollouts",
        "r.parquet",
        "--save",
        "r.rrd",
        "--json",
        "r.json",
        cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stderr
    assert "defensive-mc" in proc.stdout + proc.stderr
    result = json.loads((tmp_path / "r.json").read_text())
    assert result["method"] == "defensive-mc"
    assert result["estimate"]["p"] == pytest.approx(1e-3, rel=0.5)  # the toy (10, 5, 3, p = 0.9): exactly 1e-3
    assert result["settings"]["coin_share"] == 0.2 and result["settings"]["coin_radius_m"] == 4.0  # its own, recorded
    from pemviz.io.rollout_format import read_sidecar

    config = read_sidecar(tmp_path / "r.parquet").provenance["config"]  # the rollout file's sidecar
    assert (config["coin_share"], config["coin_radius_m"], config["method"]) == (0.2, 4.0, "defensive-mc")
    assert (tmp_path / "r.rrd").stat().st_size > 0
    again = _pemviz("estimate", "r.parquet", "--no-record", "--json", "e.json", cwd=tmp_path)
    assert again.returncode == 0, again.stderr
    log_mu = result["estimate"]["log_p"]
    assert json.loads((tmp_path / "e.json").read_text())["estimate"]["log_p"] == log_mu  # bit for bit
    assert f"log mu_hat = {log_mu:.4f} nats" in again.stdout


def test_pemviz_validate_runs_a_method_of_ones_own(tmp_path):
    proc = _pemviz(
        "validate",
        "--problems",
        "toy-1e-3",
        "--presets",
        "",
        "--baselines",
        "defensive-mc",
        "--seeds",
        "2",
        "--out",
        "v",
        cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stderr
    table = (tmp_path / "v" / "validate.md").read_text()
    assert "defensive-mc" in table and "toy-1e-3" in table


def test_a_bad_method_plugin_or_name_is_one_line(tmp_path):
    (tmp_path / "broken.py").write_text("raise RuntimeError('boom')\n")
    env = {**os.environ, "PEMVIZ_METHODS": "broken", "PYTHONPATH": str(tmp_path)}
    proc = subprocess.run(
        [sys.executable, "-m", "pemviz.cli", "run", "--method", "mine", "--no-record"],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1, proc.stderr
    assert "method plugin PEMVIZ_METHODS module broken: RuntimeError: boom" in proc.stderr
    proc = _pemviz("run", "--method", "defensive", "--no-record", cwd=tmp_path)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1, proc.stderr
    assert "use one of adaptive, mc, naive50, mixed50, ams, tilt, state, defensive-mc" in proc.stderr


def test_the_guide_shows_this_very_module():
    from conftest import doc_python_block

    assert doc_python_block("own-simulator.md", "### A method of your own") == (HERE / "user_method.py").read_text()


def test_a_method_that_cannot_add_batches_refuses_a_stop_rule(defensive):
    from dataclasses import replace

    register_method(replace(defensive, name="one-batch", extensible=False))
    try:
        with pytest.raises(
            ValueError,
            match="rel_error = 0.2 is invalid: method one-batch has no final batch to add "
            "to; use it with method adaptive, mc, naive50, mixed50, tilt, state, "
            "defensive-mc$",
        ):
            run_plan(ExperimentConfig.of(method="one-batch", rel_error=0.2))
        assert run_plan(ExperimentConfig.of(method="defensive-mc", rel_error=0.2)).open_ended
    finally:
        unregister_method("one-batch")


def user_then_most(config, simulations):
    """A method's own ``then_most``: three checks a planned rollout."""
    return 3 * simulations, "checks of its own"


def test_a_method_s_then_most_is_the_cost_line_s_last_words(defensive):
    """What a method may add after its stages is the record's to say (:attr:`Method.then_most`), in the cost line."""
    from dataclasses import replace

    from pemviz.app.form import run_cost
    from pemviz.engine.cost import LOAD_WORDS

    register_method(replace(defensive, name="checked", then_most=f"{__name__}:user_then_most"))
    try:
        text = run_cost(ExperimentConfig.of(method="checked", n_per_stage=400)).text()
        assert text.startswith("400 simulations, ") and text.endswith(" with 1,200 checks of its own")
        plain = run_cost(ExperimentConfig.of(method="defensive-mc", n_per_stage=400)).text()
        # nothing may follow its stages: a range only from the load's drift, where the machine is loaded
        assert "checks of its own" not in plain and ("up to" not in plain or plain.endswith(LOAD_WORDS)), plain
    finally:
        unregister_method("checked")


METHOD_HOMES = {
    "pemviz/estimators/builtin.py",
    "pemviz/estimators/cross_entropy.py",
    "pemviz/estimators/ce_fit.py",
    "pemviz/estimators/ce_mixture.py",
    "pemviz/estimators/ams.py",
    "pemviz/estimators/tilt.py",
    "pemviz/estimators/fixed.py",
}
"""Where a built-in method's own code lives: the only files that may name a method to branch on it."""


def _matches(pattern: str, folders: tuple[str, ...]) -> list[str]:
    import re

    from conftest import REPO

    rx = re.compile(pattern)
    out = []
    for folder in folders:
        for path in sorted((REPO / folder).rglob("*.py")):
            rel = str(path.relative_to(REPO))
            out += [
                f"{rel}:{i}: {line.strip()}"
                for i, line in enumerate(path.read_text().splitlines(), 1)
                if rx.search(line)
            ]
    return out


def test_no_branch_on_a_method_name_outside_its_home_and_no_capability_probe_in_the_upper_layers(tmp_path):
    """A method is a record, not a string to compare: ``method ==`` / ``.method in`` appear only in the methods' own
    homes, and the engine, sinks, panel, studies and commands probe no estimator with getattr / hasattr (they read
    :func:`pemviz.estimators.extras.extras`). The patterns are first shown to find a planted line."""
    branch = r"method ?(==|!=|in) |\.method ?(==|!=| in )"
    probe = r"(get|has)attr\(\s*(self\.)?(estimator|est|inner)\b"
    import re

    assert re.search(branch, 'if cfg.method == "ams":') and re.search(probe, 'getattr(estimator, "stop", None)')
    found = [m for m in _matches(branch, ("pemviz",)) if m.split(":")[0] not in METHOD_HOMES]
    assert found == []
    assert _matches(probe, ("pemviz/engine", "pemviz/sinks", "pemviz/app", "pemviz/studies", "pemviz/commands")) == []


def test_a_methods_own_settings_are_its_flags_checked_and_recorded(defensive):
    """The guide's two settings: a flag each on ``pemviz run``, read into the config by their names, refused out of
    range in one line, recorded with the run's other settings, and what the builder draws by."""
    from pemviz.cli import build_parser
    from pemviz.commands.run import config_from_args
    from pemviz.core.detectors import WindowDetector
    from pemviz.scenarios.problems import build_problem

    parser = build_parser("run", full=False)
    run = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices["run"]
    assert "--coin-share COIN_SHARE method defensive-mc's coin's share eps, a number in (0, 1): the share" in " ".join(
        run.format_help().split()
    )
    args = parser.parse_args(["run", "--method", "defensive-mc", "--coin-share", "0.2", "--coin-radius", "4"])
    cfg = config_from_args(args)
    assert (cfg.method_settings.coin_share, cfg.method_settings.coin_radius_m) == (0.2, 4.0)
    assert list(cfg.flat())[-2:] == ["coin_share", "coin_radius_m"] and cfg.value("coin_share") == 0.2
    assert cfg.replace(coin_share=0.4).method_settings.coin_share == 0.4
    assert cfg.replace(method="mc").method_settings is None and "coin_share" not in cfg.replace(method="mc").flat()
    est = build_estimator(cfg, build_problem("toy-1e-3"))
    assert isinstance(est.sampler, WindowDetector) and est.sampler.radius_m == 4.0 and est.sampler.inside.eps == 0.2
    with pytest.raises(ConfigError, match=r"^coin_share \(eps\) = 1.5 is invalid: the coin's share eps must be a "):
        ExperimentConfig.of(method="defensive-mc", coin_share=1.5)
    with pytest.raises(ConfigError, match="^--coin-share is a setting of method defensive-mc: give it with --method"):
        config_from_args(parser.parse_args(["run", "--method", "mc", "--coin-share", "0.2"]))


def test_a_methods_settings_named_by_text_are_read_when_used(defensive):
    """A method's settings class may be named as ``"module:name"`` (as the registry names a method folder's, so that
    it imports none): read when used (``Method.settings_class``), then the same as the class given itself; a text
    naming no frozen dataclass is refused when read, a class that is none when registered."""
    assert get_method("state").settings == "pemviz.methods.state:StateSettings"  # the built-in one's: by text
    text = f"{defensive.settings.__module__}:{defensive.settings.__qualname__}"
    record = register_method(dataclasses.replace(defensive, name="coin-by-text", settings=text))
    try:
        assert record.settings == text and record.settings_class() is defensive.settings
        cfg = ExperimentConfig.of(method="coin-by-text", coin_share=0.2)
        assert type(cfg.method_settings) is defensive.settings and cfg.method_settings.coin_share == 0.2
        assert list(cfg.flat())[-2:] == ["coin_share", "coin_radius_m"]
    finally:
        unregister_method("coin-by-text")
    bad = dataclasses.replace(defensive, name="coin-bad", settings="pemviz.methods.rows:ROW")  # a text: kept
    with pytest.raises(
        ValueError, match="^Method coin-bad: settings must be a frozen dataclass, got 'pemviz.setting'$"
    ):
        bad.settings_class()
    with pytest.raises(ValueError, match="^Method coin-bad: settings must be a frozen dataclass, got <class 'dict'>$"):
        dataclasses.replace(defensive, name="coin-bad", settings=dict)


def test_a_methods_own_setting_out_of_range_is_one_line(tmp_path):
    proc = _pemviz("run", "--method", "defensive-mc", "--coin-radius", "-1", "--no-record", cwd=tmp_path)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1, proc.stderr
    assert "coin_radius_m = -1.0 is invalid: the coin's radius must be none or a number > 0" in proc.stderr


def test_a_setting_added_to_the_default_method_in_its_one_file(tmp_path):
    """The guide's diff, applied to a copy of the package (pemviz/methods/adaptive.py alone), gives the cross-entropy
    sampler a setting with its flag, its check and its recorded key after the keys runs record today."""
    import re
    import shutil

    text = (HERE.parents[1] / "docs" / "own-simulator.md").read_text().split("### A setting of the default method")[1]
    diff = re.search(r"```diff\n(.*?)```", text, re.S).group(1)
    files = {line[6:] for line in diff.splitlines() if line.startswith(("--- ", "+++ "))}
    assert files == {"pemviz/methods/adaptive.py"}  # one file
    shutil.copytree(HERE.parents[1] / "pemviz", tmp_path / "pemviz", ignore=shutil.ignore_patterns("__pycache__"))
    subprocess.run(["git", "apply", "-"], input=diff, cwd=tmp_path, check=True, text=True, timeout=60)
    env = {**os.environ, "PYTHONPATH": str(tmp_path)}
    script = (
        "import json; from pemviz.config import ConfigError, ExperimentConfig\n"
        "try:\n    ExperimentConfig.of(elite_min=0)\nexcept ConfigError as exc:\n    print(exc)\n"
        "print(ExperimentConfig.of(elite_min=3).adaptive.elite_min)\n"
        "print(json.dumps(list(ExperimentConfig().flat().items())))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", script], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300, check=True
    ).stdout.splitlines()
    assert out[0] == "elite_min = 0 is invalid: the fewest elites of a stage must be a whole number >= 1"
    assert out[1] == "3"
    before = json.loads(json.dumps(list(ExperimentConfig().flat().items())))
    assert json.loads(out[2]) == [*before, ["elite_min", 1]]  # every key a run records today, same order and values
    cli = [sys.executable, "-m", "pemviz.cli", "run"]
    helped = subprocess.run([*cli, "--help"], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    words = " ".join(helped.stdout.split())  # argparse wraps the help
    assert "--elite-min ELITE_MIN fewest elites of a stage, a whole number >= 1: a stage ranks at least" in words
    refused = subprocess.run(
        [*cli, "--elite-min", "0", "--no-record"], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300
    )
    assert refused.returncode == 2 and refused.stderr.count("\n") == 1, refused.stderr
    assert "--elite-min" in refused.stderr and "a whole number >= 1" in refused.stderr, refused.stderr
