"""Saved runs re-estimate to what the run printed: ``pemviz run --save-rollouts`` writes every stage the estimate
uses with the density each rollout was weighed with, and ``pemviz estimate`` prints the same mu_hat, interval, ESS,
k-hat and verdict, stage by stage and pooled; the two weight conventions on a hand-written simulator with an exact
answer; the mean-weight check of a logged density; the version-2 fields of the format."""

from __future__ import annotations

import contextlib
import io
import json
import math
import re

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pemviz import cli
from pemviz.core.severity import severity_of_signal
from pemviz.core.weights import component_of, mean_weight, mixture_step_log_q
from pemviz.io import rollout_format
from pemviz.io import rollouts as rio
from pemviz.io.rollout_estimate import REESTIMATE_RTOL
from scipy.special import logsumexp

from conftest import estimated_log_mu


def run_and_estimate(capsys, tmp_path, *run_args: str, estimate_args: tuple[str, ...] = ()) -> tuple[str, str, dict]:
    """(the run's stdout, the estimate's stdout, the sidecar) of ``pemviz run ... --save-rollouts`` then
    ``pemviz estimate`` (its JSON document in ``tmp_path / "estimate.json"``)."""
    path = tmp_path / "r.parquet"
    assert cli.main(["run", "--no-record", "--save-rollouts", str(path), *run_args]) == 0, capsys.readouterr().err
    run = capsys.readouterr().out
    code = cli.main(
        ["estimate", str(path), "--no-record", "--json", str(tmp_path / "estimate.json"), "--overwrite", *estimate_args]
    )
    out = capsys.readouterr()
    assert code == 0, out.err
    return run, out.out, json.loads(rollout_format.sidecar_path(path).read_text())


def stage_cells(run_out: str) -> dict[int, str]:
    """stage -> failures .. verdict of the run's table (without gamma and wall time)."""
    rows = [ln for ln in run_out.splitlines() if re.match(r"^\s+\d+ +\w+ ", ln)]
    return {int(ln[:7]): " ".join(ln[27:-8].split()) for ln in rows}


def estimate_cells(est_out: str) -> dict[object, str]:
    """stage (or "final") -> failures .. verdict of the estimate's table."""
    out = {}
    for ln in est_out.splitlines():
        m = re.match(r"^\s+(\d+|final) +\S* +(\d+/\d+ .*)$", ln)
        if m:
            out[m.group(1) if m.group(1) == "final" else int(m.group(1))] = " ".join(
                m.group(2).split("   <-")[0].split()
            )
    return out


def summary_line(out: str) -> str:
    """The verdict line: the last line that gives mu_hat with its interval (or says no failure was seen)."""
    return [
        ln
        for ln in out.strip().splitlines()
        if ln.startswith(("mu_hat = ", "no failure seen in")) and ("CI" in ln or "no failure seen in" in ln)
    ][-1]


def assert_round_trip(run: str, est: str, sidecar: dict, est_log_mu: float) -> None:
    """The estimate prints the run's final row and its whole verdict line (the exact answer included), its stage rows,
    and mu_hat (``est_log_mu``: its JSON's full float) to REESTIMATE_RTOL."""
    run_final = " ".join(next(ln for ln in run.splitlines() if ln.startswith("  final "))[27:-8].split())
    cells = estimate_cells(est)
    final = cells.get("final", cells.get(sidecar["pooling"]["stages"][0]))
    assert final == run_final
    assert summary_line(est) == summary_line(run)  # with the exact answer the run printed
    by_stage = stage_cells(run)
    for k in sidecar["pooling"]["stages"]:
        assert cells[k] == by_stage[k]
    run_log_mu = float(sidecar["provenance"]["estimate"]["log_mu_hat"])  # "-inf" in JSON
    assert est_log_mu == run_log_mu or abs(math.expm1(est_log_mu - run_log_mu)) <= REESTIMATE_RTOL
    assert "warning" not in est


# ------------------------------------------------------------------------------------ round trips by preset


def test_default_run_round_trips_all_its_pooled_stages_and_its_mean_weight_is_one(tmp_path, capsys):
    run, est, sidecar = run_and_estimate(capsys, tmp_path)
    assert_round_trip(run, est, sidecar, estimated_log_mu(tmp_path / "estimate.json"))
    pooling = sidecar["pooling"]
    assert pooling["rule"] == "quadratic" and pooling["stages"][-1] == 11 and len(pooling["stages"]) > 1
    j = np.arange(1, len(pooling["stages"]) + 1)
    n = np.array([s["n"] for s in sidecar["stages"]])
    np.testing.assert_allclose(pooling["stage_weights"], j**2 * n / (j**2 * n).sum(), rtol=1e-15)
    assert sidecar["weights"] == "to-failure" and sidecar["version"] == 2
    assert all(
        s["max_weight"] == 10.0
        and [c["n"] for c in s["components"]] == [s["n"] // 10, 45 * s["n"] // 100, 45 * s["n"] // 100]
        for s in sidecar["stages"]
    )
    lines = est.splitlines()
    assert lines[1].startswith("  weights: to-failure, prod p/q over the steps before the failure step")
    assert f"<- stages {', '.join(map(str, pooling['stages']))} pooled (quadratic)" in est
    m = re.search(r"mean importance weight (\S+) \(SE (\S+)\) over (\d+) rollouts", est)
    assert abs(float(m.group(1)) - 1.0) < 4 * float(m.group(2)) and int(m.group(3)) == sum(n)
    # each rollout's severity: its min gap, and its closing speed into a gap <= 0.7 m (NaN: no contact)
    data = rio.read_rollouts(tmp_path / "r.parquet")
    dist, speed = severity_of_signal(data.signal("gap_m"), 0.7, 0.05)
    np.testing.assert_array_equal(data.min_distance, dist)
    np.testing.assert_array_equal(data.impact_speed, speed)
    assert np.isfinite(speed).any() and sidecar["version"] == 2  # the format version stays


@pytest.mark.parametrize(
    "run_args",
    [
        ("--preset", "state-ce-step", "--k", "4"),  # the presets' settings at fewer stages: the same file, 40 % of
        ("--preset", "paper"),
        ("--preset", "authors-code", "--k", "4", "--seed", "1"),  # the time (K = 10: 24 CPU-s); 1 failure here
        ("--method", "mc", "--n", "2000"),
        ("--method", "naive50", "--n", "300"),
        ("--method", "mixed50", "--n", "300"),
        ("--rel-error", "0.05"),
        ("--method", "mixed50", "--n", "300", "--rel-error", "0.3", "--max-sims", "3000"),
    ],
    ids=["state-ce-step", "paper", "authors-code", "mc", "naive50", "mixed50", "rel-error", "mixed50-rel-error"],
)
def test_every_preset_and_method_round_trips(tmp_path, capsys, run_args):
    run, est, sidecar = run_and_estimate(capsys, tmp_path, *run_args)
    assert_round_trip(run, est, sidecar, estimated_log_mu(tmp_path / "estimate.json"))
    paper_like = "paper" in run_args or "authors-code" in run_args
    assert sidecar["weights"] == ("full" if paper_like else "to-failure")
    if "--rel-error" in run_args:  # final batches added after the planned ones, pooled as the run pooled them
        planned_last = 1 if "mixed50" in run_args else 11
        assert run.count("stop: ") == 1 and max(sidecar["pooling"]["stages"]) > planned_last
        assert sidecar["pooling"]["rule"] == ("rollouts" if "mixed50" in run_args else "quadratic")
    if "authors-code" in run_args:  # the last CE stage's batch is the estimate
        assert sidecar["pooling"] == {"rule": "single", "stages": [4], "stage_weights": [1.0]}
        assert (tmp_path / "r.proposal.pt").is_file()  # one stage drawn by the proposal: its checkpoint


def test_a_tilted_run_round_trips_and_its_sidecar_names_the_tilt_without_a_weight_bound(tmp_path, capsys):
    """The tilt's rollouts are drawn by the scenario's proposal, not the target: the sidecar says so and declares no
    bound on the weights (a bound of 1 made every re-estimate warn that log_q was wrong): the toy's tilt, aimed at
    the failures, gives a mean weight below 1, as unbounded weights aimed at the failures give."""
    run, est, sidecar = run_and_estimate(capsys, tmp_path, "--scenario", "toy", "--method", "tilt", "--n", "300")
    assert_round_trip(run, est, sidecar, estimated_log_mu(tmp_path / "estimate.json"))
    assert [(s["max_weight"], [c["sampler"] for c in s["components"]]) for s in sidecar["stages"]] == [
        (None, ["the scenario's tilted proposal"])
    ]
    assert "warning" not in est and "checked above 1 only" in est


def test_chunked_runs_round_trip(tmp_path, capsys):
    # --chunk 1000 streams a stage of more than 1,000 rollouts, the path a stage above 20,000 takes in chunks of 8,192:
    # naive50 with 2,001 rollouts (chunks of 1,000, 1,000 and 1, a row group each) and a small default sampler whose
    # final batch streams
    run, est, sidecar = run_and_estimate(capsys, tmp_path, "--method", "naive50", "--n", "2001", "--chunk", "1000")
    assert_round_trip(run, est, sidecar, estimated_log_mu(tmp_path / "estimate.json"))
    assert pq.ParquetFile(tmp_path / "r.parquet").num_row_groups == 3
    (tmp_path / "r.parquet").unlink(), rollout_format.sidecar_path(tmp_path / "r.parquet").unlink()
    quick = ("--preset", "quick", "--k", "3", "--n", "40", "--n-final", "2001", "--chunk", "1000", "--seed", "2")
    run, est, sidecar = run_and_estimate(capsys, tmp_path, *quick)
    assert_round_trip(run, est, sidecar, estimated_log_mu(tmp_path / "estimate.json"))
    assert sidecar["stages"][-1]["n"] == 2001 and len(sidecar["pooling"]["stages"]) >= 2
    assert pq.ParquetFile(tmp_path / "r.parquet").num_row_groups > 3  # the stages', then the final batch's 3 chunks


def test_all_stages_are_written_on_request_and_only_the_pooled_ones_are_pooled(tmp_path, capsys):
    quick = ("--preset", "quick", "--k", "3", "--n", "40", "--n-final", "200", "--rollout-stages", "all")
    # the stages' own rollouts: no plain Monte Carlo batches after them
    run, est, sidecar = run_and_estimate(capsys, tmp_path, *quick, "--plain-fallback", "0")
    assert [s["stage"] for s in sidecar["stages"]] == [0, 1, 2, 3, 4]
    assert_round_trip(run, est, sidecar, estimated_log_mu(tmp_path / "estimate.json"))
    cells, by_stage = estimate_cells(est), stage_cells(run)
    assert all(cells[k] == by_stage[k] for k in range(5))  # pretraining and every CE stage, pooled or not


def test_ams_refuses_to_save_rollouts_in_one_line(tmp_path, capsys):
    code = cli.main(["run", "--method", "ams", "--no-record", "--save-rollouts", str(tmp_path / "a.parquet")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and "without importance weights" in err
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------------------------ the logged-density check


def test_a_file_weighed_by_one_mixture_component_is_warned_about_and_the_right_one_is_not(
    tmp_path, capsys, monkeypatch
):
    # log_q = the density of the component that drew each rollout (what version 1 wrote), not the mixture's: under
    # the mixture 0.1 p + 0.45 q1 + 0.45 q2 every weight is at most 10 and the mean is 1 +- 0.28 at 4 standard errors;
    # with the component's density the rollouts of the target weigh 1, the others almost 0: a mean near 0.1
    import pemviz.sinks.rollouts as sinks

    args = ("--preset", "quick", "--k", "4", "--n", "50", "--n-final", "300", "--seed", "3")
    _, right, _ = run_and_estimate(capsys, tmp_path, *args)
    assert "warning" not in right
    real = sinks.stage_log_q
    monkeypatch.setattr(sinks, "stage_log_q", lambda batch, *a: (batch.log_q, *real(batch, *a)[1:]))
    (tmp_path / "r.parquet").unlink(), rollout_format.sidecar_path(tmp_path / "r.parquet").unlink()
    _, wrong, _ = run_and_estimate(capsys, tmp_path, *args)
    warning = [ln for ln in wrong.splitlines() if ln.startswith("warning:")]
    assert len(warning) == 1 and "log_q is not the density that drew these rollouts" in warning[0]
    assert 0.05 < float(re.search(r"mean importance weight (\S+) is", warning[0]).group(1)) < 0.2


def test_mean_weight_check_by_hand():
    # weights 0, 0, 10, 2 under a bound of 10: mean 3, sample SE sd/2, bound SE sqrt(4 * 9) / 4 = 1.5: 2 / 1.5 < 4
    log_w = np.log([1e-300, 1e-300, 10.0, 2.0])
    check = mean_weight(log_w, np.full(4, 10.0))
    assert check.mean == pytest.approx(3.0) and check.bound_se == pytest.approx(1.5) and not check.far
    assert check.se == pytest.approx(np.std([0, 0, 10, 2], ddof=1) / 2)
    assert mean_weight(np.log([20.0, 0.1]), np.full(2, 10.0)).over_bound == 1  # a weight above its bound
    low = mean_weight(np.full(400, np.log(0.1)), np.full(400, 10.0))  # 0.1 each: 0.9 / (3 / 20) = 6 SE below 1
    assert low.far and low.z == pytest.approx(-6.0)
    assert not mean_weight(np.full(400, np.log(0.1))).far  # unbounded weights: a low mean is not checked
    assert mean_weight(np.log([50.0, 60.0, 55.0, 40.0])).far  # far above 1 in its own standard errors
    assert not mean_weight(np.zeros(10)).far  # every weight 1 (plain Monte Carlo)


# ------------------------------------------------------------------------------------ the two weight conventions


def braking_toy_log(n: int, seed: int) -> dict[str, np.ndarray]:
    """A hand-written simulator and its own full-trajectory log. A car 11 m from an obstacle moves 1 m a step for
    T = 12 steps; a detection at a gap of 2..6 m stops it for good; it fails once the gap is below 2 m (step 10).
    The target detects with 0.9 everywhere, so it fails iff it misses at the 5 gaps 6..2: mu = 0.1^5 = 1e-5 exactly.
    The tool samples detections with 0.5 at gaps <= 6 (after the failure too) and 0.9 beyond."""
    rng = np.random.default_rng(seed)
    t_steps = 12
    gap, det = np.empty((n, t_steps)), np.empty((n, t_steps), dtype=bool)
    g, stopped = np.full(n, 11.0), np.zeros(n, dtype=bool)
    for t in range(t_steps):
        q = np.where(g <= 6.0, 0.5, 0.9)
        a = rng.random(n) < q
        gap[:, t], det[:, t] = g, a
        stopped |= a & (g >= 2.0) & (g <= 6.0)
        g = np.where(stopped, g, g - 1.0)
    q_detect = np.where(gap <= 6.0, 0.5, 0.9)
    log_p = np.where(det, math.log(0.9), math.log(0.1))
    log_q = np.where(det, np.log(q_detect), np.log1p(-q_detect))
    return {"gap_m": gap, "detected": det, "log_p": log_p, "log_q": log_q}


def test_a_full_trajectory_log_reproduces_its_own_estimate_and_both_conventions_find_the_exact_answer(tmp_path, capsys):
    n, exact = 6000, 1e-5
    log = braking_toy_log(n, seed=0)
    failed = log["gap_m"].min(axis=1) < 2.0
    ratio = log["log_p"] - log["log_q"]
    w_full = np.exp(ratio[:, :11].sum(axis=1))  # the tool's own weights: prod_{t < T - 1} p / q (the paper's eq. 6)
    w_stop = np.exp(ratio[:, :10].sum(axis=1))  # every failure happens at step 10
    tool = float(np.mean(w_full * failed))
    table = pa.table(
        {
            "rollout": np.repeat(np.arange(n), 12),
            "step": np.tile(np.arange(12), n),
            **{k: v.reshape(-1) for k, v in log.items()},
        }
    )
    pq.write_table(table, tmp_path / "toy.parquet")
    (tmp_path / "toy.json").write_text(json.dumps({"formula": "G[0,11](d >= 2)", "dt_s": 0.1, "weights": "full"}))
    found = {}
    for weights in ("full", "to-failure"):
        doc = tmp_path / f"{weights}.json"
        assert (
            cli.main(
                ["estimate", str(tmp_path / "toy.parquet"), "--no-record", "--weights", weights, "--json", str(doc)]
            )
            == 0
        )
        out = capsys.readouterr().out
        assert out.splitlines()[1].startswith(f"  weights: {weights}, prod p/q over ")
        found[weights] = math.exp(estimated_log_mu(doc))
    assert found["full"] == pytest.approx(tool, rel=1e-6)
    assert found["to-failure"] == pytest.approx(float(np.mean(w_stop * failed)), rel=1e-6)
    for w in (w_full, w_stop):  # both unbiased: within 4 standard errors of the exact 1e-5
        y = w * failed
        assert abs(y.mean() - exact) < 4 * y.std(ddof=1) / math.sqrt(n)
    assert abs(found["full"] / found["to-failure"] - 1) > 0.01  # the conventions give different numbers
    assert cli.main(["estimate", str(tmp_path / "toy.parquet"), "--no-record"]) == 0  # the sidecar's convention
    out = capsys.readouterr().out
    assert "weights: full" in out.splitlines()[1] and "the convention the sidecar records" in out.splitlines()[1]
    (tmp_path / "toy.json").write_text(json.dumps({"formula": "G[0,11](d >= 2)", "dt_s": 0.1}))
    assert cli.main(["estimate", str(tmp_path / "toy.parquet"), "--no-record"]) == 0
    out = capsys.readouterr().out
    assert "weights: to-failure" in out.splitlines()[1] and "pemviz's default" in out.splitlines()[1]


def test_a_version_1_file_is_read_as_one_batch_under_its_runs_convention(tmp_path, capsys):
    # what pemviz wrote before version 2: no stage column, the run's config in the provenance (the paper's weights)
    log = braking_toy_log(500, seed=1)
    table = pa.table(
        {
            "rollout": np.repeat(np.arange(500), 12),
            "step": np.tile(np.arange(12), 500),
            **{k: v.reshape(-1) for k, v in log.items()},
        }
    )
    pq.write_table(table, tmp_path / "old.parquet")
    (tmp_path / "old.json").write_text(
        json.dumps(
            {
                "format": "pemviz-rollouts",
                "version": 1,
                "formula": "G[0,11](d >= 2)",
                "dt_s": 0.1,
                "provenance": {"stage": 1, "kind": "final", "config": {"weights_until_failure": False}},
            }
        )
    )
    assert cli.main(["estimate", str(tmp_path / "old.parquet"), "--no-record"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[1] == (
        "  weights: full, prod p/q over every step but the last (Innes & Ramamoorthy 2022, eq. 6) "
        "(the run's config in the sidecar)"
    )
    failed = log["gap_m"].min(axis=1) < 2.0
    mu = np.mean(np.exp((log["log_p"] - log["log_q"])[:, :11].sum(axis=1)) * failed)
    assert re.match(r"^\s+1 +final +\d+/500 ", out[5]) and f"{mu:.3e}" in out[5]


# ------------------------------------------------------------------------------------ the mixture's density


def test_mixture_step_density_by_hand():
    # two components, shares 0.25 / 0.75, two steps; q1 = (0.5, 0.2), q2 = (0.1, 0.9) for the actions taken:
    # q_mix(a_0) = 0.25 0.5 + 0.75 0.1 = 0.2; q_mix(a_0, a_1) = 0.25 0.1 + 0.75 0.09 = 0.0925, so q_mix(a_1 | a_0) =
    # 0.0925 / 0.2
    log_q = np.log([[[0.5, 0.2]], [[0.1, 0.9]]])
    got = mixture_step_log_q(log_q, [0.25, 0.75])
    np.testing.assert_allclose(np.exp(got), [[0.2, 0.0925 / 0.2]], rtol=1e-14)
    many = np.log(np.random.default_rng(0).uniform(0.01, 1.0, size=(3, 5, 40)))
    c = np.array([0.1, 0.45, 0.45])
    np.testing.assert_allclose(
        mixture_step_log_q(many, c).sum(axis=1), logsumexp(np.log(c)[:, None] + many.sum(axis=2), axis=0), rtol=1e-12
    )
    assert component_of(50, 10, [10, 45, 45]).tolist() == [1] * 5 + [2] * 5  # rollouts 50..59: edges at 10, 55
    assert component_of(8, 4, [10, 45]).tolist() == [0, 0, 1, 1]
    with pytest.raises(ValueError, match=r"log_q must be \[K, N, T\] and shares \[K\] > 0"):
        mixture_step_log_q(many, [0.5, 0.5])


# ------------------------------------------------------------------------------------ version-2 format fields


def tiny_table(stages: list[int], components: list[int], t_steps: int = 3) -> pa.Table:
    n = len(stages)
    return pa.table(
        {
            "rollout": np.repeat(np.arange(n), t_steps),
            "step": np.tile(np.arange(t_steps), n),
            "gap_m": np.tile(np.linspace(5.0, 1.0, t_steps), n),
            "detected": np.zeros(n * t_steps, dtype=bool),
            "log_p": np.full(n * t_steps, -0.1),
            "log_q": np.full(n * t_steps, -0.1),
            "stage": np.repeat(np.asarray(stages, dtype=np.int64), t_steps),
            "component": np.repeat(np.asarray(components, dtype=np.int64), t_steps),
        }
    )


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(st.tuples(st.integers(0, 3), st.integers(0, 2)), min_size=1, max_size=12))
def test_stage_and_component_columns_read_back_and_are_checked_against_the_sidecar(tmp_path, rows):
    stages, comps = [s for s, _ in rows], [c for _, c in rows]
    path = tmp_path / "v2.parquet"
    pq.write_table(tiny_table(stages, comps), path)
    counts = {k: np.bincount([c for s, c in rows if s == k], minlength=3).tolist() for k in sorted(set(stages))}
    side = {
        "formula": "G[0,2](d >= 2)",
        "dt_s": 0.1,
        "version": 2,
        "stages": [
            {"stage": k, "n": sum(c), "components": [{"sampler": f"q{i}", "n": x} for i, x in enumerate(c)]}
            for k, c in counts.items()
        ],
        "pooling": {
            "rule": "rollouts",
            "stages": sorted(counts),
            "stage_weights": [sum(c) / len(rows) for c in counts.values()],
        },
    }
    rollout_format.sidecar_path(path).write_text(json.dumps(side))
    data = rio.read_rollouts(path)
    assert data.stage.tolist() == stages and data.component.tolist() == comps
    first = sorted(counts)[0]
    side["stages"][0]["n"] += 1
    side["stages"][0]["components"][0]["n"] += 1
    rollout_format.sidecar_path(path).write_text(json.dumps(side))
    with pytest.raises(rollout_format.RolloutFormatError, match=f"stage {first} has n = "):
        rio.read_rollouts(path)


@settings(max_examples=100, deadline=None)
@given(
    st.recursive(
        st.none() | st.booleans() | st.integers(-3, 3) | st.floats(allow_nan=False) | st.text(max_size=4),
        lambda inner: st.lists(inner, max_size=3)
        | st.dictionaries(
            st.sampled_from(
                ["stage", "n", "kind", "components", "sampler", "max_weight", "rule", "stages", "stage_weights"]
            ),
            inner,
            max_size=4,
        ),
        max_leaves=12,
    ),
    st.sampled_from(["stages", "pooling", "weights", "objects", "noise"]),
)
def test_any_stages_pooling_or_weights_field_parses_or_is_one_format_error(value, key):
    try:
        meta = rollout_format.RolloutMeta.from_json({"formula": "G[0,2](d >= 2)", "dt_s": 0.1, key: value})
    except rollout_format.RolloutFormatError as exc:
        assert str(exc).startswith("sidecar: ") and "\n" not in str(exc)
    else:
        # written back, read the same
        assert rollout_format.RolloutMeta.from_json(meta.to_json()).to_json() == meta.to_json()


def test_a_stage_column_that_changes_within_a_rollout_is_named(tmp_path):
    table = tiny_table([1, 1], [0, 0])
    stage = table.column("stage").to_numpy().copy()
    stage[4] = 2
    pq.write_table(
        table.set_column(table.column_names.index("stage"), "stage", pa.array(stage)), tmp_path / "x.parquet"
    )
    (tmp_path / "x.json").write_text(json.dumps({"formula": "G[0,2](d >= 2)", "dt_s": 0.1}))
    with pytest.raises(
        rollout_format.RolloutFormatError, match=r"stage = 2 at rollout 1, step 1 \(row 4\) but 1 at its step 0"
    ):
        rio.read_rollouts(tmp_path / "x.parquet")


# ------------------------------------------------------------------------- several objects with measurement errors


@pytest.fixture(scope="module")
def cut_in_file(tmp_path_factory):
    """``pemviz run --scenario cut-in`` (small) with ``--save-rollouts``: (run stdout, estimate stdout, sidecar,
    path)."""
    tmp = tmp_path_factory.mktemp("cut_in")
    path = tmp / "r.parquet"
    # K = 4: its pooled stages (4 and the final batch, 5) are mixtures with the target (3 components each; K = 10 cost
    # 2.5 times as much); the stages' own file (no plain Monte Carlo after them)
    args = ["--scenario", "cut-in", "--method", "adaptive", "--k", "4", "--n", "50", "--n-final", "150"]
    args += ["--plain-fallback", "0"]
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert cli.main(["run", "--no-record", "--save-rollouts", str(path), *args]) == 0
    run = out.getvalue()
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert cli.main(["estimate", str(path), "--no-record", "--json", str(tmp / "estimate.json")]) == 0
    return run, out.getvalue(), json.loads(rollout_format.sidecar_path(path).read_text()), path


def test_a_cut_in_run_round_trips_each_cars_detections_and_errors(cut_in_file):
    """Five cars, missed and mislocated (format version 3): the estimate from the file is the run's (1e-9), stage by
    stage and pooled, though a mixture stage's per-step densities now hold the errors' log densities (> 0 allowed)."""
    run, est, sidecar, path = cut_in_file
    assert (sidecar["version"], sidecar["objects"], sidecar["noise"]) == (3, 5, ["range_error_m", "lateral_error_m"])
    assert sidecar["dt_s"] == 0.1 and sidecar["signals"]["clearance"] == "clearance_m"
    run_log_mu = float(sidecar["provenance"]["estimate"]["log_mu_hat"])
    est_log_mu = estimated_log_mu(path.parent / "estimate.json")
    assert math.isfinite(run_log_mu) and abs(math.expm1(est_log_mu - run_log_mu)) <= REESTIMATE_RTOL
    run_final = " ".join(next(ln for ln in run.splitlines() if ln.startswith("  final "))[27:-8].split())
    cells = estimate_cells(est)
    assert cells["final"] == run_final
    by_stage = stage_cells(run)
    for k in sidecar["pooling"]["stages"]:
        assert cells[k] == by_stage[k]
    assert "warning" not in est
    data = rio.read_rollouts(path)
    n, t = data.n, data.n_steps
    assert data.detected.shape == (n, t, 5) and data.noise.shape == (n, t, 5, 2)
    assert data.noise_names == ("range_error_m", "lateral_error_m")
    assert (data.noise[~data.detected] == 0.0).all() and (data.noise[data.detected] != 0.0).mean() > 0.99
    # each rollout's severity: its min clearance, and its closing speed into a clearance <= 0 (NaN: no contact)
    clearance = data.signal("clearance_m")
    np.testing.assert_array_equal(data.min_distance, clearance.min(axis=1))
    np.testing.assert_array_equal(data.impact_speed, severity_of_signal(clearance, 0.0, 0.1)[1])
    # pooled stages drawn from a mixture with the target: their per-step density of the errors is not clipped at 0
    assert any(len(sidecar["stages"][i]["components"]) == 3 for i in range(len(sidecar["stages"])))


def test_a_cut_in_file_is_refused_a_pem_to_recompute_and_names_a_missing_cars_column(cut_in_file, tmp_path, capsys):
    _, _, _, path = cut_in_file
    assert cli.main(["estimate", str(path), "--no-record", "--pem", "ml-nn"]) == 2
    err = capsys.readouterr().err
    assert "--pem: " in err and "holds 5 object(s) a step with errors ['range_error_m', 'lateral_error_m']" in err
    table = pq.read_table(path).drop(["detected_3"])
    broken = tmp_path / "b.parquet"
    pq.write_table(table, broken)
    side = json.loads(rollout_format.sidecar_path(path).read_text())
    side.pop("table_sha256")
    rollout_format.sidecar_path(broken).write_text(json.dumps(side))
    with pytest.raises(rollout_format.RolloutFormatError, match="missing column 'detected_3'"):
        rio.read_rollouts(broken)
    side["objects"] = 0
    rollout_format.sidecar_path(broken).write_text(json.dumps(side))
    with pytest.raises(rollout_format.RolloutFormatError, match="objects must be an integer >= 1"):
        rio.read_rollouts(broken)


def test_the_exact_answer_is_printed_only_for_the_run_s_own_failure_and_density(tmp_path, capsys):
    # the run's PEM and a crash of its specification: the run's exact answer; another failure event: none is known
    run, est, _ = run_and_estimate(capsys, tmp_path, "--k", "3", "--n", "100", "--n-final", "300")
    assert "; exact 1.984e-15 (relative error" in summary_line(est) and summary_line(est) == summary_line(run)
    code = cli.main(["estimate", str(tmp_path / "r.parquet"), "--no-record", "--failure", "metric", "--metric", "agm"])
    out = capsys.readouterr()
    assert code == 0, out.err
    assert "exact" not in summary_line(out.out)
