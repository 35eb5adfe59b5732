"""An operating design domain (ODD): parameters drawn per rollout from distributions (pemviz.core.odd,
pemviz.core.odd_rollouts, pemviz.scenarios.odd), checked against the toy's closed form, the parser's errors and the
seed contract."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pemviz.config import ConfigError, ExperimentConfig
from pemviz.core.odd import ODD, ODDError, bin_log_weights, odd_map, parse_distribution
from pemviz.engine.experiment import Experiment
from pemviz.scenarios.registry import problem_for
from pemviz.scenarios.toy.simulator import ToyParams, toy_log_failure_probability

TOY_ODD = (("total", 10), ("safe", 3), ("braking", "~choice(5, 6, 7)"))
EXACT = (1e-3 + 1e-4 + 1e-5) / 3  # the toy (10, b, 3, p = 0.9): (1 - 0.9)^(b - 2), b = 5, 6, 7 alike


def test_distributions_parse_draw_and_bin():
    u = parse_distribution("uniform(10, 14)")
    assert u.text == "uniform(10, 14)" and u.support() == (10.0, 14.0)
    np.testing.assert_allclose(u.ppf(np.array([0.0, 0.25, 0.5])), [10.0, 11.0, 12.0])
    edges, probs = u.bins(4)
    np.testing.assert_allclose(edges, [10, 11, 12, 13, 14]) and np.testing.assert_allclose(probs, 0.25)
    n = parse_distribution("normal(7.5, 0.5)")
    assert n.ppf(np.array([0.5]))[0] == pytest.approx(7.5) and n.ppf(np.array([0.975]))[0] == pytest.approx(
        7.5 + 1.959964 * 0.5, rel=1e-6
    )
    c = parse_distribution("choice(19.5: 1, 20: 3)")
    assert c.weights == (0.25, 0.75) and c.text == "choice(19.5: 0.25, 20: 0.75)"
    np.testing.assert_array_equal(c.ppf(np.array([0.0, 0.2499, 0.25, 0.99])), [19.5, 19.5, 20.0, 20.0])
    assert parse_distribution("choice(5, 6, 7)").text == "choice(5, 6, 7)"


@pytest.mark.parametrize(
    "text, message",
    [
        ("unif(1, 2)", "unknown distribution 'unif'; use one of uniform, normal, choice"),
        ("uniform(2, 2)", r"uniform\(2, 2\) has an empty support; need a < b"),
        ("uniform(1)", "uniform takes 2 numbers, a, b; got 1"),
        ("normal(1, 0)", "needs sd > 0"),
        ("normal(1, x)", "'x' is not a number"),
        ("choice()", "choice\\(\\) has no value"),
        ("choice(1: -1, 2: 1)", "weights must be >= 0"),
        ("choice(1, 1)", "values must be distinct"),
        ("uniform(1, inf)", "is not a finite number"),
        ("12", "is not a distribution"),
    ],
)
def test_a_bad_distribution_is_one_line(text, message):
    with pytest.raises(ODDError, match=message) as err:
        parse_distribution(text, where="x")
    assert "\n" not in str(err.value)


@settings(max_examples=60, deadline=None)
@given(a=st.floats(-1e6, 1e6), width=st.floats(1e-6, 1e6), u=st.lists(st.floats(0, 1, exclude_max=True), min_size=1))
def test_uniform_round_trips_its_text_and_draws_inside_its_support(a, width, u):
    law = parse_distribution(f"uniform({a!r}, {a + width!r})")
    again = parse_distribution(f"uniform({law.args[0]!r}, {law.args[1]!r})")
    assert again == law
    x = law.ppf(np.array(u))
    assert np.all(x >= law.args[0]) and np.all(x <= law.args[1])


@settings(max_examples=60, deadline=None)
@given(
    values=st.lists(st.integers(-50, 50), min_size=1, max_size=6, unique=True),
    weights=st.lists(st.floats(0.01, 10), min_size=6, max_size=6),
)
def test_choice_weights_are_its_draws_frequencies(values, weights):
    text = "choice(" + ", ".join(f"{v}: {w!r}" for v, w in zip(values, weights, strict=False)) + ")"
    law = parse_distribution(text)
    assert sum(law.weights) == pytest.approx(1.0)
    u = (np.arange(20_000) + 0.5) / 20_000  # a fine grid of uniforms: frequencies within 1 / 20,000
    x = law.ppf(u)
    for v, w in zip(law.args, law.weights, strict=True):
        assert np.mean(x == v) == pytest.approx(w, abs=1e-4)


def test_a_bin_estimate_is_unbiased_in_closed_form():
    """bin_log_weights: the mean of w 1[fail] / P(bin) over all rollouts is p(fail | bin)."""
    values = np.repeat([5.0, 6.0, 7.0], 4)
    failed = np.array([1, 1, 0, 0, 1, 0, 0, 0, 0, 0, 0, 0], bool)
    edges, probs = parse_distribution("choice(5, 6, 7)").bins()
    lw = bin_log_weights(values, np.zeros(12), edges, probs, 0)
    assert np.exp(lw[failed]).sum() / 12 == pytest.approx(2 / 4)  # 2 of the 4 rollouts at 5 failed
    assert np.all(lw[4:] == -np.inf)


def test_the_toy_over_an_odd_by_plain_monte_carlo_holds_its_closed_form():
    problem = problem_for(ExperimentConfig.of(scenario="toy", scenario_params=TOY_ODD))
    assert math.exp(problem.exact_log_p) == pytest.approx(EXACT, rel=1e-12)
    done = Experiment(
        ExperimentConfig.of(scenario="toy", scenario_params=TOY_ODD, method="mc", n_per_stage=200_000, seed=3),
        problem=problem,
    ).run()
    e = done.final.estimate
    assert e.log_ci[0] <= problem.exact_log_p <= e.log_ci[1] and abs(math.exp(e.log_mu_hat) / EXACT - 1) < 0.15


def test_the_toy_over_an_odd_by_the_default_sampler_and_its_map():
    """The default sampler over seeds 0-9: near the closed form, no ``reliable`` verdict outside x2 and every interval
    it prints (its weights passing the verdict's checks, a failure in every bin of its map) holding it; the map's bins
    hold each braking distance's closed form."""
    problem = problem_for(ExperimentConfig.of(scenario="toy", scenario_params=TOY_ODD))
    ratios = []
    for seed in range(10):
        e = (
            Experiment(ExperimentConfig.of(scenario="toy", scenario_params=TOY_ODD, seed=seed), problem=problem)
            .run()
            .final.estimate
        )
        ratios.append(math.exp(e.log_mu_hat) / EXACT)
        assert e.verdict != "reliable" or (0.5 < ratios[-1] < 2 and e.covers(math.log(EXACT))), (seed, e.summary())
        if seed == 1:  # ESS 90, k-hat 0.06, x0.07: no failure at b = 5 (89 % of p_ODD) caps it, or it said reliable
            assert ratios[-1] < 0.1 and e.verdict == "doubtful" and "no failure in braking = 5" in e.reason
    assert np.median(np.abs(np.array(ratios) - 1)) < 0.1 and sum(0.5 < r < 2 for r in ratios) >= 8
    rollouts = problem.simulate(100_000, problem.target, problem.target, np.random.default_rng(1))
    failed = problem.failed(rollouts)
    values = rollouts.observations[:, 0, [rollouts.observation_names.index("braking")]]
    bins = odd_map(problem.odd, values, np.zeros(rollouts.n), failed, np.zeros(rollouts.n))
    for b, exact in zip(bins, (1e-3, 1e-4, 1e-5), strict=True):
        lo, hi = b.estimate.log_ci
        assert lo <= math.log(exact) <= hi, (b.label, b.estimate.summary())
    assert bins[0].share == pytest.approx(1e-3 / (1e-3 + 1e-4 + 1e-5), abs=0.12)  # 0.90; 3 failures at b = 6


def test_an_odd_stream_is_the_same_rollouts_at_any_chunk_size():
    problem = problem_for(ExperimentConfig.of(scenario="toy", scenario_params=TOY_ODD))
    whole = problem.simulate(3000, problem.target, problem.target, np.random.default_rng(7))
    for size in (1000, 777):
        chunks = list(problem.stream(3000, problem.target, problem.target, np.random.default_rng(7), chunk_size=size))
        assert sum(c.n for c in chunks) == 3000
        np.testing.assert_array_equal(np.concatenate([c.observations for c in chunks]), whole.observations)
        np.testing.assert_array_equal(np.concatenate([c.detected for c in chunks]), whole.detected)
    drawn = whole.observations[:, 0, whole.observation_names.index("braking")]
    assert set(np.unique(drawn)) == {5.0, 6.0, 7.0} and abs(np.mean(drawn == 5.0) - 1 / 3) < 0.03


def test_braking_draws_its_start_per_rollout():
    cfg = ExperimentConfig.of(scenario_params=(("ego_speed0_mps", "~uniform(6, 12)"),), n_per_stage=50)
    problem = problem_for(cfg)
    batch = problem.simulate(400, problem.target, problem.target, np.random.default_rng(0))
    names = batch.observation_names
    speed0 = batch.observations[:, 0, names.index("ego_speed0_mps")]
    np.testing.assert_array_equal(batch.observations[:, 0, names.index("ego_speed_mps")], speed0)  # it starts there
    assert 6.0 <= speed0.min() and speed0.max() <= 12.0 and problem.exact_log_p is None and problem.look_ahead is None


def test_a_fixed_parameter_is_todays_run():
    """Without a distribution nothing changes: the same problem and rollouts as before."""
    problem = problem_for(
        ExperimentConfig.of(scenario="toy", scenario_params=(("total", 10), ("safe", 3), ("braking", 5)))
    )
    assert problem.odd is None and problem.exact_log_p == pytest.approx(
        toy_log_failure_probability(ToyParams(10, 5, 3, 0.9))
    )


@pytest.mark.parametrize(
    "param, message",
    [
        ("braking~unif(5, 6)", "braking~unif\\(5, 6\\): unknown distribution 'unif'"),
        ("braking~uniform(5, 7)", "braking takes a whole number: draw it from choice"),
        ("braking~choice(5, 60)", "its value 60 is out of the parameter's range"),
        (
            "total~choice(9, 10)",
            "the toy scenario cannot draw total per rollout \\(its parameters that can be drawn: " "braking\\)",
        ),
        ("braking~choice()", "choice\\(\\) has no value"),
    ],
)
def test_a_bad_odd_on_the_command_line_is_one_line_exit_2(param, message, tmp_path):
    proc = pemviz_cli(
        tmp_path,
        *TOY_RUN,
        "--param",
        param,
        "--no-record",
    )
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1, proc.stderr
    assert __import__("re").search(message, proc.stderr), proc.stderr
    with pytest.raises(ConfigError):
        ExperimentConfig.of(scenario="toy", scenario_params=(("total", 10), ("safe", 3), tuple(param.split("~", 1))))
    assert list(tmp_path.iterdir()) == []


def test_a_scenario_that_draws_nothing_says_how_one_declares_a_parameter_drawn():
    """A user's scene without ``random_params`` said only "(its parameters that can be drawn: none)"."""
    from pemviz.scenarios.odd import odd_value

    with pytest.raises(ValueError) as err:
        odd_value("crossing", "brake_mps2", "uniform(8, 9)", ())
    assert str(err.value) == (
        "brake_mps2~...: the crossing scenario cannot draw brake_mps2 per rollout (it draws none: a scenario names "
        "those it can by random_params= and odd= in its Scenario record); give it a value, brake_mps2=VALUE"
    )


def test_an_odd_run_writes_its_map_and_re_estimates_to_its_p(tmp_path):
    import json

    proc = pemviz_cli(
        tmp_path,
        *TOY_RUN,
        "--param",
        "braking~choice(5, 6, 7)",
        "--save",
        "o.rrd",
        "--save-rollouts",
        "o.parquet",
        "--json",
        "o.json",
        "--report",
        "o.html",
    )
    assert proc.returncode == 0, proc.stderr
    assert "most of p_ODD: braking = 5" in proc.stdout
    doc = json.loads((tmp_path / "o.json").read_text())
    assert [b["lo"] for b in doc["odd_map"]["bins"]] == [4.5, 5.5, 6.5]
    page = (tmp_path / "o.md").read_text()  # the report's Markdown twin: the map as a section of its own
    assert "## Operating design domain" in page and "| braking in [4.5, 5.5) | 0.33 |" in page
    again = pemviz_cli(tmp_path, "estimate", "o.parquet", "--no-record", "--json", "e.json")
    assert again.returncode == 0, again.stderr
    said = json.loads((tmp_path / "e.json").read_text())["estimate"]["log_p"]
    assert said == pytest.approx(doc["estimate"]["log_p"], rel=1e-12, abs=0)  # the run's p_ODD again
    recorded = recorded_map(tmp_path / "o.rrd")  # the recording's ODD view: the document's numbers
    assert [round(b["log_p"] / math.log(10), 9) for b in doc["odd_map"]["bins"]] == [
        round(x, 9) for x in recorded["/odd/braking/log10_p"]
    ]
    assert "Most of p_ODD: **braking = 5**" in recorded["/odd/map"]


def recorded_map(path) -> dict:
    """The ODD view of a recording read back through rerun's own API: the map's table and each ``/odd/<name>/...``
    series over the ``odd_bin`` timeline, in bin order."""
    rr = pytest.importorskip("rerun")
    pytest.importorskip("datafusion", reason="rerun-sdk[catalog] reads recordings back")
    with rr.server.Server(datasets={"run": [str(path)]}) as server:
        ds = server.client().get_dataset("run")
        table = ds.reader(index="odd_bin").to_arrow_table().to_pylist()
        static = ds.reader(index=None).to_arrow_table()
    out: dict = {"/odd/map": static.column("/odd/map:TextDocument:text").to_pylist()[0][0]}
    for row in sorted(table, key=lambda r: r["odd_bin"]):
        for key, value in row.items():
            if key.startswith("/odd/") and key.endswith(":Scalars:scalars") and value is not None:
                out.setdefault(key.split(":")[0], []).append(value[0])
    return out


def test_an_odd_is_its_parameters_in_order():
    odd = ODD((("a", parse_distribution("uniform(0, 1)")), ("b", parse_distribution("choice(1, 2)"))))
    assert odd.names == ("a", "b") and odd.text() == "a ~ uniform(0, 1), b ~ choice(1, 2)"
    np.testing.assert_allclose(odd.draw(np.array([[0.5, 0.75]])), [[0.5, 2.0]])


def test_a_branch_over_an_odd_keeps_each_parents_parameters_and_prefix():
    """Splitting and the counterfactuals replay a rollout from a step: its drawn parameters come with it."""
    problem = problem_for(ExperimentConfig.of(scenario="toy", scenario_params=TOY_ODD))
    parents = problem.simulate(50, problem.target, problem.target, np.random.default_rng(0))
    children = problem.branch(parents, np.arange(10, 20), np.full(10, 3), problem.target, np.random.default_rng(1))
    col = parents.observation_names.index("braking")
    np.testing.assert_array_equal(children.observations[:, 0, col], parents.observations[10:20, 0, col])
    np.testing.assert_array_equal(children.detected[:, :3], parents.detected[10:20, :3])


def test_the_pair_map_is_each_cells_failure_rate_under_plain_monte_carlo_and_unbiased_under_weights():
    """Hand-made rollouts over x ~ uniform(0, 1) (5 bins of 0.2) and y ~ choice(1, 2): a cell's p is the failure
    rate of its rollouts with plain Monte Carlo's weights, and the weighted mean / P(cell) under importance weights."""
    from pemviz.core.odd_pair import pair_map

    odd = ODD((("x", parse_distribution("uniform(0, 1)")), ("y", parse_distribution("choice(1, 2)"))))
    x = np.repeat([0.1, 0.3, 0.5, 0.7, 0.9], 8)  # 8 rollouts a column, 4 with y = 1 and 4 with y = 2
    y = np.tile([1.0, 1.0, 1.0, 1.0, 2.0, 2.0, 2.0, 2.0], 5)
    failed = (x > 0.6) & ((np.arange(40) % 4) < (y == 2) * 2 + 1)  # y = 1: 1 of 4 fail, y = 2: 3 of 4 (x > 0.6)
    values = np.stack([x, y], axis=1)
    plain = pair_map(odd, values, np.zeros(40), failed, np.zeros(40))
    assert plain is not None and plain.names == ("x", "y") and len(plain.cells) == 2 and len(plain.cells[0]) == 5
    rates = np.array([[e.mu_hat if e.n_failures else 0.0 for e in row] for row in plain.cells])
    np.testing.assert_allclose(rates, [[0, 0, 0, 0.25, 0.25], [0, 0, 0, 0.75, 0.75]], rtol=1e-12)
    # shares: P(cell) p_cell over their sum, P(cell) = 0.2 * 0.5 for every cell
    np.testing.assert_allclose(plain.shares[:, 3:], [[0.125, 0.125], [0.375, 0.375]], rtol=1e-12)
    assert plain.top() in ((3, 1), (4, 1)) and "x in [0.6, 0.8) and y in" in plain.cell_label(3, 1)
    # importance weights w: the estimate of cell (a, b) is sum(w 1[fail] in cell) / (N P(cell))
    log_w = np.log(np.linspace(0.5, 1.5, 40))
    weighted = pair_map(odd, values, log_w, failed, np.zeros(40))
    w = np.exp(log_w)
    inside = (x > 0.6) & (x < 0.8) & (y == 2)
    expected = np.sum(w * failed * inside) / (40 * 0.1)
    assert weighted is not None and weighted.cells[1][3].mu_hat == pytest.approx(expected, rel=1e-12)
    assert pair_map(ODD((("x", parse_distribution("uniform(0, 1)")),)), x[:, None], np.zeros(40), failed, x) is None


def test_a_run_over_two_parameters_prints_records_and_keeps_their_heat_map(tmp_path):
    import json

    proc = pemviz_cli(
        tmp_path,
        "run",
        "--preset",
        "quick",
        "--param",
        "gap0_m~uniform(11, 13)",
        "--param",
        "ego_speed0_mps~uniform(9, 10.4)",
        "--save",
        "b.rrd",
        "--json",
        "b.json",
    )
    assert proc.returncode == 0, proc.stderr
    assert "odd map of the pair (gap0_m, ego_speed0_mps): p(failure | cell)" in proc.stdout
    pair = json.loads((tmp_path / "b.json").read_text())["odd_map"]["pair"]
    assert pair["names"] == ["gap0_m", "ego_speed0_mps"] and len(pair["cells"]) == 5 and len(pair["cells"][0]) == 5
    assert pair["x_edges"][0] == 11 and pair["y_edges"][-1] == 10.4
    shares = [c["share"] for row in pair["cells"] for c in row]
    assert sum(shares) == pytest.approx(1.0, abs=1e-9)
    rr = pytest.importorskip("rerun")
    pytest.importorskip("datafusion", reason="rerun-sdk[catalog] reads recordings back")
    with rr.server.Server(datasets={"run": [str(tmp_path / "b.rrd")]}) as server:
        client = server.client()
        ds = client.get_dataset("run")
        static = ds.reader(index=None).to_arrow_table()
    assert any(c.startswith("/odd/pair:Tensor") for c in static.column_names), static.column_names


TOY_RUN = ("run", "--scenario", "toy", "--param", "total=10", "--param", "safe=3")
"""``pemviz run`` of the toy of these tests (its other parameters at their defaults)."""


def pemviz_cli(cwd, *argv: str) -> subprocess.CompletedProcess:
    """``pemviz ARGV`` in a new process in ``cwd``, its output captured."""
    return subprocess.run(
        [sys.executable, "-m", "pemviz.cli", *argv], cwd=cwd, capture_output=True, text=True, timeout=300
    )
