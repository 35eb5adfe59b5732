"""The user guide's "Your system in 30 minutes" (docs/your-system.md) runs as written: every python block of the page
in order (a PEM fitted with scikit-learn, a crosswalk of two pedestrians, the problem with its exact answer, the
scenario registered and checked, the default run and plain Monte Carlo), the numbers it quotes are what they print,
and they agree with independent truth: the enumeration with plain Monte Carlo of the same simulator, the default
run's interval with the enumeration. Its command-line form (``PEMVIZ_SCENARIOS``, ``pemviz run``, ``pemviz
estimate``) runs on the page's module and gives the run's number back."""

from __future__ import annotations

import contextlib
import io
import json
import math
import os
import re
import shlex
import subprocess
from pathlib import Path

import numpy as np
import pytest
from pemviz.config import ExperimentConfig
from pemviz.engine.experiment import Experiment
from pemviz.io.rollout_estimate import estimate_rollouts
from pemviz.io.rollouts import read_rollouts
from pemviz.scenarios.registry import registered, unregister

from conftest import BIN, REPO

PAGE = REPO / "docs" / "your-system.md"
NAME = "my-crosswalk"
MODULE_BLOCKS = 4
"""The first four python blocks are the module ``my_crosswalk.py`` the page has the reader save."""


def blocks(language: str = "python") -> list[str]:
    return re.findall(rf"```{language}\n(.*?)```", PAGE.read_text(), re.S)


def prose() -> str:
    """The page with its line breaks as spaces (a number quoted across a line break reads as one phrase)."""
    return " ".join(PAGE.read_text().split())


@pytest.fixture(scope="module")
def guide():
    """Every python block of the page run in order in one namespace, with what they printed; the scenario the fourth
    block registers is unregistered afterwards."""
    namespace: dict = {"__name__": "your_system_guide"}
    printed = io.StringIO()
    try:
        with contextlib.redirect_stdout(printed):
            for block in blocks():
                exec(compile(block, str(PAGE), "exec", dont_inherit=True), namespace)  # as written: no __future__
        yield namespace, printed.getvalue()
    finally:
        if NAME in registered():
            unregister(NAME)


def test_the_page_has_the_blocks_the_tests_run_and_is_in_the_nav():
    assert len(blocks()) == MODULE_BLOCKS + 2 and len(blocks("bash")) == 1 and len(blocks("text")) == 1
    text = PAGE.read_text()
    assert text.startswith("# Your system in 30 minutes\n") and len(text.splitlines()) <= 260
    assert "your-system.md" in (REPO / "mkdocs.yml").read_text()


def test_the_fit_recovers_the_law_the_table_was_drawn_from_and_the_page_quotes_it(guide):
    """5,000 rows, 80 % of them visible: the fitted coefficients within 0.5 (intercept), 0.03 (per metre of range) and
    0.15 (per metre off axis) of the law's 4.5, -0.3 and -0.5, the error share within 0.005 of 10 %."""
    ns, printed = guide
    fit, share = ns["fit"], ns["error_share"]
    b0, (b_range, b_off) = fit.intercept_[0], fit.coef_[0]
    assert abs(b0 - 4.5) < 0.5 and abs(b_range + 0.3) < 0.03 and abs(b_off + 0.5) < 0.15 and abs(share - 0.1) < 0.005
    assert f"logit p = {b0:.2f} - {-b_range:.3f} range_m - {-b_off:.3f} off_axis_m" in prose()
    assert f"error of {100 * share:.1f} % of the range" in prose()
    assert f"fit: logit p = {b0:.2f} {b_range:+.3f} range_m {b_off:+.3f} off_axis_m" in printed
    camera = ns["CAMERA"]
    hidden = np.array([[10.0, 0.0, 1.0], [10.0, 1.0, 1.0]])  # the same pedestrian behind the van, then in sight
    logit = camera.detect_logit(hidden)
    assert logit[0] == -np.inf and logit[1] == pytest.approx(b0 + 10 * b_range + b_off)


def test_the_scenario_passes_the_conformance_kit(guide):
    _, printed = guide
    report = "6 checks passed (schema, problem, determinism, features, rollout-file, recording)"
    assert f"scenario {NAME}: {report}" in printed
    assert "skipped twin" in printed and "skipped drawing" in printed  # no single simulator, no drawing


def test_the_scenes_state_features_are_the_time_each_pedestrian_is_away(guide):
    """At the start the car (10 m/s) is 32 m and 29 m from pedestrians A and B: 3.2 s and 2.9 s away; the problem
    replays them from a batch's events, named as the page declares them."""
    ns, _ = guide
    problem = ns["problem"]
    batch = problem.simulate(20, problem.target, problem.target, np.random.default_rng(0))
    f = problem.features(batch, None)
    assert f.feature_names == ("speed_mps", "braking") and f.object_feature_names == ("time_to_reach_s",)
    np.testing.assert_allclose(f.object_feature("time_to_reach_s")[:, 0], [[3.2, 2.9]] * 20, rtol=1e-12)
    np.testing.assert_array_equal(f.feature("speed_mps"), batch.signal("speed_mps"))


def test_the_exact_answer_is_what_plain_monte_carlo_finds_and_the_default_run_holds_it(guide):
    """The enumeration (1.072e-3, quoted) against the page's 100,000 plain Monte Carlo rollouts drawn from the PEM:
    within 4 binomial standard errors; the default run's interval (seed 0) holds it and its mu_hat is within 10 %."""
    ns, printed = guide
    problem, est, mc = ns["problem"], ns["done"].final.estimate, ns["mc"].final.estimate
    exact = math.exp(problem.exact_log_p)
    assert exact == pytest.approx(1.072e-3, rel=5e-4) and f"p = {exact:.3e}".replace("e-0", "e-") in prose()
    assert mc.n == 100_000 and abs(mc.mu_hat - exact) < 4 * math.sqrt(exact * (1 - exact) / mc.n)
    assert f"{mc.n_failures} failures in 100,000 rollouts, mu_hat = {mc.mu_hat:.3e}" in prose()
    assert f"[{math.exp(mc.log_ci[0]):.2e}, {math.exp(mc.log_ci[1]):.2e}]" in prose()
    assert mc.log_ci[0] < problem.exact_log_p < mc.log_ci[1]
    assert est.log_ci[0] < problem.exact_log_p < est.log_ci[1] and abs(est.mu_hat / exact - 1) < 0.10
    assert est.verdict == "reliable"
    quoted = blocks("text")[0].strip()
    assert quoted == est.summary(problem.exact_log_p) and quoted in printed.splitlines()
    assert est.mu_hat < exact and f"{round(100 * (1 - est.mu_hat / exact))} % below it" in prose()


def test_seeds_1_to_3_give_what_the_page_says(guide):
    """Each reliable, its interval holding the enumeration, its ratio to it the page's (0.91, 0.95, 0.97, rounded)."""
    ns, _ = guide
    problem = ns["problem"]
    ratios = []
    for seed in (1, 2, 3):
        est = Experiment(ExperimentConfig.of(seed=seed), problem=problem).run().final.estimate
        assert est.verdict == "reliable" and est.log_ci[0] < problem.exact_log_p < est.log_ci[1]
        ratios.append(est.mu_hat / math.exp(problem.exact_log_p))
    assert [f"{r:.2f}" for r in ratios] == ["0.91", "0.95", "0.97"]  # the seed contract: the same runs anywhere
    assert "Seeds 1-3 give 0.91, 0.95 and 0.97 times it" in prose()


def test_a_run_s_rollout_file_re_estimates_and_its_why_line_names_the_pedestrians(guide, command_line):
    """The page's run from the command line (:func:`command_line`), with its rollout file and the console's why-line:
    the file re-estimates to the page's in-process mu_hat (the seed contract) within 1e-9 and names dist_m as its h
    column; the why-line (quoted) calls the objects by their labels."""
    ns, _ = guide
    folder, run, _ = command_line
    side = json.loads((folder / "r.rollouts.json").read_text())
    assert side["h_column"] == "dist_m" and side["dt_s"] == 0.1 and side["objects"] == 2
    data = read_rollouts(folder / "r.parquet")
    again = estimate_rollouts(data, data.log_p, data.log_q, log_p_seen=side["provenance"]["estimate"]["log_p_seen"])
    ran = ns["done"].final.estimate.log_mu_hat
    assert again.estimate.log_mu_hat == pytest.approx(ran, rel=1e-9, abs=1e-9)
    (why,) = [line for line in run.stdout.splitlines() if line.startswith("why: ")]
    assert "object 0" not in why
    quoted = (
        "37 misses and 8 measurement errors before the failure at step 28; decisive alone: pedestrian B missed "
        "at step 11; pedestrian A missed at step 12;"
    )
    assert why.startswith("why: the most likely failure (stage 11; ") and why.split("): ", 1)[1].startswith(quoted)
    assert f"`why: the most likely failure (stage 11; ...): {quoted} ...`" in prose()


def pemviz(command: str, cwd: Path) -> subprocess.CompletedProcess:
    """The page's ``command`` through the installed console script (the ``pemviz`` beside this interpreter), run in
    ``cwd`` as a user runs it: ``PEMVIZ_SCENARIOS`` set as the page sets it, nothing pointing at the plugin's folder
    (this environment's ``PYTHONPATH`` passed through without it: where pemviz is not installed, it names pemviz)."""
    path = [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p and Path(p).resolve() != cwd.resolve()]
    env = {**os.environ, "RERUN_ANALYTICS": "false", "PEMVIZ_SCENARIOS": "my_crosswalk"}
    env.pop("PYTHONPATH", None)
    if path:
        env["PYTHONPATH"] = os.pathsep.join(path)
    args = shlex.split(command.split("#", 1)[0])
    assert args[0] == "pemviz" and (BIN / "pemviz").is_file(), f"no console script {BIN / 'pemviz'}: install pemviz"
    return subprocess.run(
        [str(BIN / "pemviz"), *args[1:]], cwd=cwd, env=env, capture_output=True, text=True, timeout=600
    )


@pytest.fixture(scope="module")
def command_line(tmp_path_factory):
    """The first four blocks saved as my_crosswalk.py and the page's ``pemviz`` commands run as written in that folder
    (the estimate with ``--json e.json``, its result kept in full): (folder, the run, the estimate)."""
    folder = tmp_path_factory.mktemp("my-crosswalk")
    (folder / "my_crosswalk.py").write_text("\n\n".join(blocks()[:MODULE_BLOCKS]))
    commands = [line for line in blocks("bash")[0].splitlines() if line.startswith("pemviz ")]
    assert [c.split()[1] for c in commands] == ["run", "estimate"]
    run = pemviz(commands[0], folder)
    assert run.returncode == 0, run.stderr[-2000:]
    estimate = pemviz(f"{commands[1].split('#', 1)[0]} --json e.json", folder)
    assert estimate.returncode == 0, estimate.stderr[-2000:]
    return folder, run, estimate


def test_the_command_line_form_runs_the_saved_module_and_estimate_gives_its_number_back(guide, command_line):
    """The first four blocks saved as my_crosswalk.py, found through PEMVIZ_SCENARIOS in the folder the installed
    ``pemviz`` runs in: the page's ``pemviz`` commands as written; the run prints the page's line and a why-line in the
    objects' names, writes the recording and the rollout file, and ``pemviz estimate`` gives the run's log mu_hat back
    within 1e-9."""
    assert "export PEMVIZ_SCENARIOS=my_crosswalk  # in the folder of my_crosswalk.py" in blocks("bash")[0]
    folder, run, estimate = command_line
    assert blocks("text")[0].strip() in run.stdout.splitlines()
    why = [line for line in run.stdout.splitlines() if line.startswith("why: ")]
    assert len(why) == 1 and "pedestrian B missed at step 11; pedestrian A missed at step 12" in why[0]
    assert (folder / "r.rrd").stat().st_size > 0
    logged = json.loads((folder / "e.json").read_text())["estimate"]["log_p"]
    ran = guide[0]["done"].final.estimate.log_mu_hat  # the page's run in this process: the same seed, the same run
    assert logged == pytest.approx(ran, rel=1e-9, abs=1e-9)
    assert f"log mu_hat = {ran:.4f} nats" in estimate.stdout
    assert json.loads((folder / "r.rollouts.json").read_text())["h_column"] == "dist_m"
    assert not list(folder.glob("recordings/estimate-*"))  # --no-record


def test_the_command_line_form_outside_the_module_s_folder_says_what_to_set(tmp_path):
    """From a folder without my_crosswalk.py: one line, exit 2, naming the folder searched and what to set."""
    run = pemviz("pemviz run --scenario my-crosswalk --no-record", tmp_path)
    assert run.returncode == 2 and run.stdout == "" and "Traceback" not in run.stderr
    assert run.stderr.splitlines() == [
        "pemviz run: error: scenario plugin PEMVIZ_SCENARIOS module my_crosswalk: no module my_crosswalk in the "
        f"current folder ({tmp_path.resolve()}) nor on the Python path: run pemviz in the folder of my_crosswalk.py, "
        "or set PYTHONPATH to that folder"
    ]
