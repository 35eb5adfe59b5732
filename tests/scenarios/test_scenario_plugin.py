"""A scenario of one's own as one module and one registration (the user guide's ``my_car_scenario``): every command
takes it like pemviz's own scenarios (``pemviz run`` with its recording and parameters, ``pemviz validate``, the
conformance kit), found through ``PEMVIZ_SCENARIOS``; a plugin that cannot be loaded is one line."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import PLUGIN_SCENARIO_HEADING, REPO, doc_python_block, verify_rrd

HEADING = PLUGIN_SCENARIO_HEADING


@pytest.fixture(scope="module")
def plugin(tmp_path_factory) -> Path:
    """A folder holding the guide's module, as a user would save it."""
    folder = tmp_path_factory.mktemp("plugin")
    (folder / "my_car_scenario.py").write_text(doc_python_block("own-simulator.md", HEADING))
    return folder


def pemviz(*args: str, cwd: Path, plugin: Path, modules: str = "my_car_scenario") -> subprocess.CompletedProcess:
    env = {
        **os.environ,
        "RERUN_ANALYTICS": "false",
        "PEMVIZ_SCENARIOS": modules,
        "PYTHONPATH": os.pathsep.join((str(plugin), str(REPO))),
    }
    return subprocess.run(
        [sys.executable, "-m", "pemviz.cli", *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=600
    )


def test_the_guides_scenario_runs_with_its_recording_and_parameters(plugin, tmp_path):
    proc = pemviz(
        "run",
        "--scenario",
        "my-car",
        "--param",
        "start_gap_m=28",
        "--n",
        "200",
        "--n-final",
        "1000",
        "--save",
        "my-car.rrd",
        cwd=tmp_path,
        plugin=plugin,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "my-car scenario (start_gap_m=28.0 m)" in proc.stdout
    assert "exact" in proc.stdout.splitlines()[-1] or any("exact" in line for line in proc.stdout.splitlines())
    verify_rrd(tmp_path / "my-car.rrd")
    assert (tmp_path / "my-car.result.json").exists()


def test_the_exact_answer_is_the_enumeration_and_the_estimate_finds_it(plugin, monkeypatch):
    """In this process: the registry builds the problem with its exact answer, which the independent enumeration of
    ``tests/scenarios/test_simulator_protocol.py`` confirms for the default parameters (2.8576e-5, the guide's number),
    and a run's interval holds it."""
    monkeypatch.syspath_prepend(str(plugin))
    sys.modules.pop("my_car_scenario", None)
    from pemviz.config import ExperimentConfig
    from pemviz.engine.experiment import Experiment
    from pemviz.scenarios import registry

    try:
        __import__("my_car_scenario")
        assert "my-car" in registry.registered()
        cfg = ExperimentConfig.of(
            scenario="my-car",
            n_stages=8,
            n_per_stage=200,
            n_final=2000,
            smoothing=1.0,
            quantile_level=0.9,
            ce_epochs=200,
            pretrain_epochs=1000,
            learning_rate=1e-2,
            plain_fallback=0,  # the stages' own interval (the guide's run, with plain Monte Carlo after it, is tested
        )  # in tests/scenarios/test_simulator_protocol.py)
        problem = registry.problem_for(cfg)
        assert math.exp(problem.exact_log_p) == pytest.approx(2.8576e-5, rel=1e-3)
        est = Experiment(cfg, problem=problem).run().final.estimate
        assert est.log_ci[0] < problem.exact_log_p < est.log_ci[1]
        from pemviz.testing import check_scenario

        report = check_scenario("my-car")
        assert "determinism" in str(report)
    finally:
        if "my-car" in registry._REGISTRY:
            registry.unregister("my-car")
        sys.modules.pop("my_car_scenario", None)


def test_validate_runs_the_guides_scenario_against_its_exact_answer(plugin, tmp_path):
    proc = pemviz(
        "validate",
        "--problems",
        "my-car",
        "--presets",
        "quick",
        "--baselines",
        "mc",
        "--seeds",
        "2",
        "--out",
        str(tmp_path / "v"),
        cwd=tmp_path,
        plugin=plugin,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    table = (tmp_path / "v" / "validate.md").read_text()
    assert "| my-car | 2.858e-05 |" in table


def test_a_plugin_that_cannot_be_imported_is_one_line(plugin, tmp_path):
    proc = pemviz("run", "--scenario", "my-car", "--no-record", cwd=tmp_path, plugin=plugin, modules="no_such_mod")
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "PEMVIZ_SCENARIOS module no_such_mod" in lines[0], proc.stderr
    assert "Traceback" not in proc.stderr


def test_an_unknown_scenario_lists_the_registered_ones(plugin, tmp_path):
    proc = pemviz("run", "--scenario", "my-bike", "--no-record", cwd=tmp_path, plugin=plugin)
    assert proc.returncode == 2
    assert "use one of braking, cut-in, cut-in-rare, toy, crowd, crossing, my-car" in proc.stderr


def test_a_module_is_found_in_the_current_folder_as_python_m_finds_it(tmp_path, monkeypatch):
    """Named by the variable, a module (or a package's module) in the current folder imports with nothing on the
    path; one that is nowhere says what to set; a module found whose own import fails keeps that import's error."""
    from pemviz.plugins import PluginNotFound, import_here

    (tmp_path / "here_mod.py").write_text("import here_sibling\nVALUE = here_sibling.VALUE + 1\n")
    (tmp_path / "here_sibling.py").write_text("VALUE = 41\n")
    (tmp_path / "here_pkg").mkdir()
    (tmp_path / "here_pkg" / "__init__.py").write_text("")
    (tmp_path / "here_pkg" / "scenario.py").write_text("VALUE = 7\n")
    (tmp_path / "here_broken.py").write_text("import no_such_dependency_xyz\n")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "path", [p for p in sys.path if p not in ("", str(tmp_path))])
    for name in ("here_mod", "here_sibling", "here_pkg", "here_pkg.scenario", "here_broken"):
        monkeypatch.delitem(sys.modules, name, raising=False)
    import_here("here_mod", "PEMVIZ_SCENARIOS")
    import_here("here_pkg.scenario", "PEMVIZ_METHODS")
    assert sys.modules["here_mod"].VALUE == 42 and sys.modules["here_pkg.scenario"].VALUE == 7
    assert sys.path[-1] == str(tmp_path)  # appended: nothing installed is shadowed
    with pytest.raises(ModuleNotFoundError, match="no_such_dependency_xyz"):
        import_here("here_broken", "PEMVIZ_SCENARIOS")
    with pytest.raises(PluginNotFound) as missing:
        import_here("here_pkg.nothing", "PEMVIZ_METHODS")
    assert str(missing.value) == (
        f"no module here_pkg.nothing in the current folder ({tmp_path}) nor on the Python path: run pemviz in the "
        "folder of the package here_pkg/, or set PYTHONPATH to that folder"
    )
