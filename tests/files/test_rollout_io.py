"""Logged rollouts (Parquet + JSON sidecar) and ``pemviz estimate``: round trips give the run's mu_hat to
1e-12 with the log_p / log_q columns and recomputed from the PEM and the proposal; malformed files give one
error naming the rollout and step and write nothing."""

from __future__ import annotations

import dataclasses
import json
import math
import re
import shutil
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from pemviz import cli
from pemviz.config import ExperimentConfig
from pemviz.core.detectors import ConstantDetector, action_log_prob
from pemviz.core.estimate import estimate
from pemviz.core.plan import RunPlan
from pemviz.core.rollouts import RolloutBatch
from pemviz.core.sampling import Proposal, load_proposal
from pemviz.core.severity import rollout_severity
from pemviz.engine.events import FinalEstimate, RolloutChunk, RunFinished, RunStarted, StageStarted
from pemviz.engine.experiment import Experiment
from pemviz.estimators.ce_fit import FitOptions, ce_update, pretrain_proposal
from pemviz.io import rollout_format, rollout_table, rollout_writer
from pemviz.io import rollouts as rio
from pemviz.io.rollout_estimate import REESTIMATE_RTOL, detector_log_prob, estimate_rollouts, pem_log_prob
from pemviz.io.rollout_sidecars import braking_meta
from pemviz.pem import load_pem, save_pem
from pemviz.presets import PRESETS
from pemviz.scenarios.braking.failures import severity
from pemviz.scenarios.braking.problem import braking_problem
from pemviz.scenarios.problems import problem_for
from pemviz.sinks.rollouts import RolloutSink

from conftest import estimated_log_mu, run_cli, verify_rrd

LOG_MU_RE = re.compile(r"log mu_hat = (\S+) nats")


@pytest.fixture(scope="module")
def pem():
    return load_pem()


@pytest.fixture(scope="module")
def naive_run(tmp_path_factory, pem):
    """``naive50`` with N = 200 (146 crashes, weights ~1e-50), its final batch saved by the run's listener."""
    path = tmp_path_factory.mktemp("naive") / "naive.parquet"
    finals = []
    sink = RolloutSink(path)
    cfg = ExperimentConfig.of(method="naive50", n_per_stage=200, seed=1)
    Experiment(
        cfg, [sink, lambda ev: finals.append(ev) if isinstance(ev, FinalEstimate) else None], problem=problem_for(cfg)
    ).run()
    assert sink.written == path
    return path, finals[0].estimate


def same_mu(log_a: float, log_b: float) -> bool:
    """mu_hat equal to REESTIMATE_RTOL (1e-9) relative: |mu_a / mu_b - 1| <= 1e-9."""
    return abs(math.expm1(log_a - log_b)) <= REESTIMATE_RTOL


def estimate_cli(capsys, *args: str) -> tuple[int, str, str]:
    code = cli.main(["estimate", *args])
    out = capsys.readouterr()
    return code, out.out, out.err


# ------------------------------------------------------------------------------------ round trips


def test_run_rollouts_read_back_with_their_columns_give_the_runs_mu_hat_to_1e_12(naive_run):
    path, run_estimate = naive_run
    data = rio.read_rollouts(path)
    assert (data.n, data.n_steps, data.observation_names) == (
        200,
        100,
        ("gap_m", "ego_speed_mps", "lead_speed_mps", "brake_pending"),
    )
    result = estimate_rollouts(data, data.log_p, data.log_q)
    assert run_estimate.n_failures == result.estimate.n_failures > 100
    assert same_mu(result.estimate.log_mu_hat, run_estimate.log_mu_hat)
    assert result.estimate.nll_mean == pytest.approx(run_estimate.nll_mean, rel=1e-12)
    assert result.estimate.ess == pytest.approx(run_estimate.ess, rel=1e-12)
    meta = json.loads(rollout_format.sidecar_path(path).read_text())
    assert meta["formula"] == "G[0,99](d >= 2)" and meta["dt_s"] == 0.05 and meta["proposal"] == "naive50"
    assert meta["units"]["gap_m"] == "m" and meta["units"]["log_p"] == "nats"
    assert meta["provenance"]["estimate"]["log_mu_hat"] == run_estimate.log_mu_hat


def test_each_rollout_carries_its_severity_as_the_braking_scene_s_severity_gives_it(naive_run):
    # min gap and impact speed (closing speed into a gap <= 0.7 m; null where no contact), one value per rollout
    path, _ = naive_run
    data = rio.read_rollouts(path)
    want = [severity(data.signal("gap_m")[i]) for i in range(data.n)]
    np.testing.assert_array_equal(data.min_distance, [w.min_gap_m for w in want])
    np.testing.assert_array_equal(data.impact_speed, [w.contact_speed_mps for w in want])
    contact = np.isfinite(data.impact_speed)
    assert 0 < contact.sum() < data.n and (data.impact_speed[contact] > 0).all()
    table = pq.read_table(path, columns=list(rollout_table.SEVERITY_COLUMNS))
    assert table.column("impact_speed_mps").null_count == (~contact).sum() * data.n_steps
    assert table.column("min_distance_m").null_count == 0


def test_run_rollouts_without_the_columns_recomputed_from_the_pem_and_sampler_give_the_same_mu_hat(
    naive_run, pem, tmp_path, capsys
):
    path, run_estimate = naive_run
    data = rio.read_rollouts(path)
    assert data.salient is not None
    np.testing.assert_array_equal(pem_log_prob(data, pem), data.log_p)  # the run's numbers, bit for bit
    np.testing.assert_array_equal(detector_log_prob(data, ConstantDetector(0.5)), data.log_q)
    # the PEM on the salient variables the general way (order-free grid products, float32's precision) agrees
    general = action_log_prob(pem.logit(data.salient.reshape(-1, 11)).reshape(200, 100), data.detected[..., 0])
    np.testing.assert_allclose(general, data.log_p, rtol=0, atol=1e-5)
    # a copy without log_p / log_q: the sidecar names the PEM and the sampler
    bare = tmp_path / "bare.parquet"
    rollout_writer.write_rollouts(
        bare,
        data.to_batch(),
        data.meta,
        salient=data.salient,
        log_probs=False,
        stage=data.stage,
        component=data.component,
    )
    assert "log_p" not in pq.read_schema(bare).names
    assert not set(rollout_table.SEVERITY_COLUMNS) & set(pq.read_schema(bare).names)  # a file without severity columns
    old = rio.read_rollouts(bare)
    assert old.min_distance is None and old.impact_speed is None
    for k, args in enumerate(([str(bare)], [str(path), "--pem", "ml-nn", "--proposal", "naive50"])):
        doc = tmp_path / f"estimate{k}.json"
        code, out, err = estimate_cli(capsys, *args, "--no-record", "--json", str(doc))
        assert code == 0, err
        assert "recomputed" in out
        assert same_mu(estimated_log_mu(doc), run_estimate.log_mu_hat)
    code, out, err = estimate_cli(capsys, str(bare), "--log-q-column", "--no-record")
    assert code == 2 and "has no log_q column" in err


def test_adaptive_rollouts_round_trip_through_a_proposal_checkpoint(tmp_path, capsys):
    """A proposal after a CE stage samples a batch; the listener snapshots it at sampling time; the file's
    columns and the recomputation from the PEM file and the checkpoint both give the batch's own mu_hat."""
    weak = dataclasses.replace(load_pem(), temperature=4.0)  # a less confident PEM: crashes in 60 rollouts
    pem_file = save_pem(weak, tmp_path / "weak.pt")
    problem = braking_problem(weak)
    rng = np.random.default_rng(2)
    proposal = Proposal()
    pem_batch = problem.simulate(40, problem.target, problem.target, rng)
    pretrain_proposal(proposal, pem_batch.signal("gap_m"), pem_batch.detected[..., 0], FitOptions(100, 1e-2))
    r = problem.robustness(pem_batch, "classic")
    ce_update(
        proposal,
        pem_batch.signal("gap_m"),
        pem_batch.detected[..., 0],
        pem_batch.log_p,
        pem_batch.log_q,
        r <= np.sort(r)[3],
        FitOptions(50, 1e-2),
        smoothing=0.5,
    )
    batch = problem.simulate(60, proposal, problem.target, rng)
    failed = problem.failed(batch)
    truth = estimate(batch.log_weight(), failed, batch.log_p[:, :99].sum(axis=1))
    assert truth.n_failures > 0

    path = tmp_path / "adaptive.parquet"
    sink = RolloutSink(path, pem=str(pem_file))
    cfg = ExperimentConfig.of(**PRESETS["paper"], pem=str(pem_file))  # weights over T - 1 steps, as `truth` above
    sink(
        RunStarted(
            cfg,
            str(problem.formula),
            problem.curve_grid,
            problem.target_curve(),
            problem.view,
            RunPlan.of([(3, "final", 60)]),
        )
    )
    sink(StageStarted(3, "final", 60))
    sink(RolloutChunk(3, "final", 0, batch, batch.log_weight(), sampler=proposal))
    with torch_no_grad():
        for p in proposal.parameters():
            p.add_(0.1)  # the proposal moves on after sampling; the checkpoint must not
    sink(RunFinished(FinalEstimate(truth, 160, 0.0), ()))
    ckpt = tmp_path / "adaptive.proposal.pt"
    assert ckpt.is_file() and json.loads(rollout_format.sidecar_path(path).read_text())["proposal"] == ckpt.name

    data = rio.read_rollouts(path)
    paper_weights = estimate_rollouts(data, data.log_p, data.log_q, weights="full").estimate
    assert same_mu(paper_weights.log_mu_hat, truth.log_mu_hat)
    np.testing.assert_array_equal(detector_log_prob(data, load_proposal(ckpt)), batch.log_q)
    bare = tmp_path / "bare.parquet"
    rollout_writer.write_rollouts(
        bare, data.to_batch(), data.meta, log_probs=False, stage=data.stage, component=data.component
    )  # no salient columns: the gap
    meta = json.loads(rollout_format.sidecar_path(bare).read_text())
    assert meta["proposal"] == "adaptive.proposal.pt" and meta["pem"] == str(pem_file)
    for k, args in enumerate(([str(bare)], [str(bare), "--pem", str(pem_file), "--proposal", str(ckpt)])):
        doc = tmp_path / f"estimate{k}.json"
        code, out, err = estimate_cli(capsys, *args, "--no-record", "--json", str(doc))
        assert code == 0, err
        assert f"{truth.n_failures}/60" in out
        assert same_mu(estimated_log_mu(doc), truth.log_mu_hat)


@pytest.fixture
def chunked(pem, monkeypatch):
    """The braking problem with stages above 300 rollouts streamed in chunks of 128."""
    import dataclasses

    import pemviz.engine.experiment as engine
    from pemviz.scenarios.braking.batched import iter_batched

    monkeypatch.setattr(engine, "STREAM_ABOVE", 300)
    return dataclasses.replace(
        braking_problem(pem),
        stream=lambda n, sampler, target, rng: iter_batched(None, n, sampler, target, rng, chunk_size=128),
    )


STREAMED = ExperimentConfig.of(
    n_stages=1,
    n_per_stage=100,
    n_final=1000,
    pretrain_rollouts=50,
    ce_epochs=5,
    pretrain_epochs=5,
    seed=3,
    target_share=0.0,
    plain_share=0.0,
    plain_fallback=0,
)
"""A run whose final batch (1,000 rollouts from one sampler) is streamed in 8 chunks by :func:`chunked` (and no plain
Monte Carlo follows it)."""


def test_a_streamed_final_batch_is_written_chunk_by_chunk_and_reads_back_whole(tmp_path, chunked):
    """Above STREAM_ABOVE the engine never holds the final batch: the sink writes each chunk as a row group."""
    sink = RolloutSink(tmp_path / "big.parquet")
    chunks = []
    done = Experiment(
        STREAMED,
        [sink, lambda e: isinstance(e, RolloutChunk) and e.kind == "final" and chunks.append(e)],
        problem=chunked,
    ).run()
    assert [c.start for c in chunks] == list(range(0, 1000, 128)) and pq.ParquetFile(sink.written).num_row_groups == 8
    data = rio.read_rollouts(sink.written)
    assert data.detected.shape == (1000, 100, 1)
    whole = RolloutBatch.concatenate([c.batch for c in chunks])
    np.testing.assert_array_equal(data.detected, whole.detected)
    np.testing.assert_array_equal(data.log_q, whole.log_q)
    assert data.meta.provenance["estimate"]["n"] == done.final.estimate.n


def test_a_run_cancelled_while_writing_leaves_no_rollout_file(tmp_path, chunked):
    import threading

    from pemviz.engine.events import RunCancelled

    cancel = threading.Event()
    sink = RolloutSink(tmp_path / "r.parquet")

    def cancel_at_the_third_chunk(e):
        if isinstance(e, RolloutChunk) and e.kind == "final" and e.start >= 256:
            cancel.set()

    out = Experiment(STREAMED, [sink, cancel_at_the_third_chunk], cancel, problem=chunked).run()
    assert isinstance(out, RunCancelled) and sink.written is None
    assert list(tmp_path.iterdir()) == []


def torch_no_grad():
    import torch

    return torch.no_grad()


def test_a_hand_written_file_with_a_minimal_sidecar_gives_the_hand_computed_estimate(tmp_path):
    """3 rollouts of 4 steps; rollouts 0 and 2 drop below 2 m, at steps 2 and 3. log w over the steps before the
    failure: rollout 0: 2 x (-1.0 - -0.5) = -1.0; rollout 2: 3 x (-2.0 - -0.25) = -5.25. mu_hat = (e^-1 + e^-5.25) / 3;
    over the first T - 1 = 3 steps (the paper's weights) rollout 0 has -1.5 instead."""
    table = pa.table(
        {
            "rollout": np.repeat(np.array([10, 11, 12], dtype=np.int32), 4),
            "step": np.tile(np.arange(4, dtype=np.int16), 3),
            "gap_m": np.array([9, 5, 1.5, 1, 9, 8, 7, 6, 9, 4, 3, 1.9], dtype=np.float32),
            "detected": np.array([1, 0, 0, 0, 1, 1, 1, 1, 0, 1, 0, 0], dtype=np.int8),
            "log_p": np.repeat([-1.0, -0.1, -2.0], 4),
            "log_q": np.repeat([-0.5, -0.1, -0.25], 4),
            "note": ["ignored"] * 12,
        }
    )
    pq.write_table(table, tmp_path / "mine.parquet")
    (tmp_path / "mine.json").write_text(json.dumps({"formula": "G[0,3](d >= 2)", "dt_s": 0.1}))
    data = rio.read_rollouts(tmp_path / "mine.parquet")
    assert list(data.rollout_ids) == [10, 11, 12]
    res = estimate_rollouts(data, data.log_p, data.log_q).estimate
    assert res.n_failures == 2
    assert res.log_mu_hat == pytest.approx(math.log((math.exp(-1.0) + math.exp(-5.25)) / 3), rel=1e-14)
    assert res.ess == pytest.approx((math.exp(-1.0) + math.exp(-5.25)) ** 2 / (math.exp(-2) + math.exp(-10.5)))
    assert res.nll_mean == pytest.approx((2.0 + 6.0) / 2)  # -log p over the steps before each failure
    paper = estimate_rollouts(data, data.log_p, data.log_q, weights="full").estimate
    assert paper.log_mu_hat == pytest.approx(math.log((math.exp(-1.5) + math.exp(-5.25)) / 3), rel=1e-14)


def test_a_files_parameter_term_divides_each_rollouts_weight_and_a_bad_one_is_one_line(tmp_path):
    """The hand-written file above over an ODD: ``log_q_params`` 0.7 (rollout 0) and -0.2 (rollout 2), drawn from a
    proposal over the parameters: mu_hat = (e^(-1 - 0.7) + e^(-5.25 + 0.2)) / 3; a value that changes along a rollout,
    and a sidecar's ``odd_parameters`` that is not a list of names, are one line each."""
    table = pa.table(
        {
            "rollout": np.repeat(np.array([0, 1, 2], dtype=np.int32), 4),
            "step": np.tile(np.arange(4, dtype=np.int16), 3),
            "gap_m": np.array([9, 5, 1.5, 1, 9, 8, 7, 6, 9, 4, 3, 1.9]),
            "gap0_m": np.repeat([9.0, 9.0, 9.0], 4),
            "detected": np.array([1, 0, 0, 0, 1, 1, 1, 1, 0, 1, 0, 0], dtype=np.int8),
            "log_p": np.repeat([-1.0, -0.1, -2.0], 4),
            "log_q": np.repeat([-0.5, -0.1, -0.25], 4),
            "log_q_params": np.repeat([0.7, 0.3, -0.2], 4),
        }
    )
    pq.write_table(table, tmp_path / "odd.parquet")
    sidecar = {"formula": "G[0,3](d >= 2)", "dt_s": 0.1, "odd_parameters": ["gap0_m"]}
    (tmp_path / "odd.json").write_text(json.dumps(sidecar))
    data = rio.read_rollouts(tmp_path / "odd.parquet")
    assert data.meta is not None and data.meta.odd_parameters == ("gap0_m",)
    np.testing.assert_array_equal(data.log_q_params, [0.7, 0.3, -0.2])
    res = estimate_rollouts(data, data.log_p, data.log_q).estimate
    assert res.log_mu_hat == pytest.approx(math.log((math.exp(-1.7) + math.exp(-5.05)) / 3), rel=1e-14)
    changing = table.set_column(7, "log_q_params", pa.array(np.r_[np.repeat([0.7, 0.3], 4), [-0.2, -0.2, 0.1, -0.2]]))
    pq.write_table(changing, tmp_path / "odd.parquet")
    with pytest.raises(
        rollout_format.RolloutFormatError, match=r"log_q_params = 0\.1 at rollout 2, step 2 .* a rollout has one"
    ):
        rio.read_rollouts(tmp_path / "odd.parquet")
    (tmp_path / "odd.json").write_text(json.dumps({**sidecar, "odd_parameters": "gap0_m"}))
    with pytest.raises(rollout_format.RolloutFormatError, match=r"odd_parameters must be a list of column names"):
        rio.read_rollouts(tmp_path / "odd.parquet")


def test_cli_run_then_estimate_prints_the_runs_mu_hat_and_writes_a_recording(tmp_path, capsys):
    rollouts, recording = tmp_path / "mixed.parquet", tmp_path / "estimate.rrd"
    code = cli.main(
        ["run", "--method", "mixed50", "--n", "50", "--seed", "3", "--no-record", "--save-rollouts", str(rollouts)]
    )
    run = capsys.readouterr()
    assert code == 0, run.err
    doc = tmp_path / "estimate.json"
    est = run_cli(
        "estimate", str(rollouts), "--save", str(recording), "--json", str(doc)
    )  # the entry point, end to end
    assert est.returncode == 0, est.stderr
    run_said = json.loads(rollout_format.sidecar_path(rollouts).read_text())["provenance"]["estimate"]
    run_log_mu = run_said["log_mu_hat"]
    assert same_mu(estimated_log_mu(doc), run_log_mu)
    assert LOG_MU_RE.search(run.out).group(1) == f"{run_log_mu:.4f}"
    assert LOG_MU_RE.search(est.stdout).group(1) == LOG_MU_RE.search(run.out).group(1)  # one format: 4 decimals
    said = json.loads(doc.read_text())
    assert said["format"] == "pemviz-estimate"
    assert (said["estimate"]["n_failures"], said["estimate"]["n"]) == (run_said["n_failures"], run_said["n"])
    assert f"result: {doc}" in est.stderr
    again = run_cli("estimate", str(rollouts), "--no-record", "--json", str(doc))  # an existing file: refused
    assert again.returncode == 2 and again.stderr.count("\n") == 1 and "--overwrite" in again.stderr, again.stderr
    assert f"rollouts: {rollouts}" in run.err
    assert recording.stat().st_size > 10_000 and not (tmp_path / "estimate.rrd.partial").exists()
    verify_rrd(recording)
    assert cli.main(["run", "--n", "5", "--save-rollouts", str(tmp_path / "x.csv"), "--no-record"]) == 2
    assert "--save-rollouts" in capsys.readouterr().err and not (tmp_path / "x.csv").exists()


# ------------------------------------------------------------------------------------ malformed files


@pytest.fixture(scope="module")
def small_file(tmp_path_factory, pem):
    """6 braking rollouts from the 50 % detector, with salient variables and log-probabilities."""
    problem = braking_problem(pem)
    batch = problem.simulate(6, ConstantDetector(0.5), problem.target, np.random.default_rng(0))
    path = tmp_path_factory.mktemp("small") / "small.parquet"
    rollout_writer.write_rollouts(
        path,
        batch,
        braking_meta(pem="ml-nn", proposal="naive50"),
        salient=rollout_table.braking_salient(batch.signal("gap_m")),
        severity=rollout_severity(problem, batch),
    )
    return path


def _set(table: pa.Table, name: str, array: pa.Array) -> pa.Table:
    return table.set_column(table.column_names.index(name), name, array)


def _values(table: pa.Table, name: str) -> np.ndarray:
    return table.column(name).to_numpy().copy()


def _row(rollout: int, step: int) -> int:
    return rollout * 100 + step


def _nan_gap(t):
    gap = _values(t, "gap_m")
    gap[_row(3, 41)] = np.nan
    return _set(t, "gap_m", pa.array(gap))


def _string_gap(t):
    return _set(t, "gap_m", pa.array([f"{g:.3f}" for g in _values(t, "gap_m")]))


def _swap_steps(t):
    order = np.arange(t.num_rows)
    order[[_row(2, 10), _row(2, 11)]] = order[[_row(2, 11), _row(2, 10)]]
    return t.take(order)


def _short_rollout(t):
    return t.take(np.delete(np.arange(t.num_rows), _row(4, 99)))


def _split_rollout(t):
    order = np.concatenate([np.arange(0, 50), np.arange(100, 200), np.arange(50, 100), np.arange(200, 600)])
    return t.take(order)


def _detected_two(t):
    det = _values(t, "detected").astype(np.int64)
    det[_row(1, 5)] = 2
    return _set(t, "detected", pa.array(det))


def _positive_log_p(t):
    lp = _values(t, "log_p")
    lp[_row(0, 3)] = 0.5
    return _set(t, "log_p", pa.array(lp))


def _null_speed(t):
    v = _values(t, "lead_speed_mps")
    mask = np.zeros(v.size, dtype=bool)
    mask[_row(2, 7)] = True
    return _set(t, "lead_speed_mps", pa.array(v, mask=mask))


def _changed_min_distance(t):
    d = _values(t, "min_distance_m")
    d[_row(1, 5)] += 1.0
    return _set(t, "min_distance_m", pa.array(d))


def _negative_impact_speed(t):
    v = _values(t, "impact_speed_mps")
    v[_row(4, 0)] = -1.0
    return _set(t, "impact_speed_mps", pa.array(v))


def _float_steps(t):
    return _set(t, "step", pa.array(_values(t, "step").astype(np.float64)))


MALFORMED = {
    "missing-column": (lambda t: t.drop_columns(["detected"]), r"missing column 'detected'; required: rollout, step"),
    "missing-salient": (
        lambda t: t.drop_columns(["salient_loc_z"]),
        r"salient-variable columns incomplete: " r"missing salient_loc_z",
    ),
    "wrong-dtype": (
        _string_gap,
        r"column 'gap_m' has type string \(e\.g\. '12\.293' at rollout 0, step 0 \(row 0\)\); " r"it must hold numbers",
    ),
    "wrong-dtype-step": (_float_steps, r"column 'step' has type double .*it must hold integers"),
    "nan-gap": (_nan_gap, r"gap_m is NaN at rollout 3, step 41 \(row 341\); values must be finite"),
    "steps-out-of-order": (_swap_steps, r"rollout 2, step 11 \(row 210\): steps out of order, expected step 10"),
    "different-lengths": (
        _short_rollout,
        r"rollout 4 has 99 steps but rollout 0 has 100: rollout 4 ends after " r"step 98",
    ),
    "rollout-not-contiguous": (_split_rollout, r"rollout 0, step 50 \(row 150\): rollout 0 appears again"),
    "detected-not-boolean": (_detected_two, r"detected = 2 at rollout 1, step 5 \(row 105\)"),
    "positive-log-p": (_positive_log_p, r"log_p = 0\.5 > 0 at rollout 0, step 3 \(row 3\)"),
    "null-value": (_null_speed, r"column 'lead_speed_mps' is missing a value \(null\) at rollout 2, step 7"),
    "severity-half": (
        lambda t: t.drop_columns(["impact_speed_mps"]),
        r"severity columns incomplete: " r"'min_distance_m' without 'impact_speed_mps'",
    ),
    "severity-changes": (
        _changed_min_distance,
        r"min_distance_m = \S+ at rollout 1, step 5 \(row 105\) but \S+ at "
        r"its step 0; a rollout has one min_distance_m",
    ),
    "impact-speed-negative": (
        _negative_impact_speed,
        r"impact_speed_mps = -1\.0 at rollout 4, step 0 \(row 400\): an " r"impact speed is a positive number",
    ),
}


@pytest.mark.parametrize("case", list(MALFORMED))
def test_malformed_file_gives_one_error_naming_rollout_and_step_and_writes_nothing(
    case, small_file, tmp_path, monkeypatch, capsys
):
    mutate, message = MALFORMED[case]
    bad = tmp_path / "bad.parquet"
    pq.write_table(mutate(pq.read_table(small_file)), bad)
    shutil.copy(rollout_format.sidecar_path(small_file), rollout_format.sidecar_path(bad))
    with pytest.raises(rollout_format.RolloutFormatError, match=message):
        rio.read_rollouts(bad)
    monkeypatch.chdir(tmp_path)
    before = sorted(p.name for p in tmp_path.iterdir())
    for extra in ([], ["--save", str(tmp_path / "out.rrd")]):
        code, out, err = estimate_cli(capsys, str(bad), *extra)
        assert code == 2 and out == ""
        assert len(err.strip().splitlines()) == 1 and re.search(message, err), err
        assert err.startswith(f"pemviz estimate: error: {bad}: ")
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # no recording, no partial, no recordings/


def test_sidecar_problems_are_named(small_file, tmp_path):
    bad = tmp_path / "s.parquet"
    shutil.copy(small_file, bad)
    with pytest.raises(rollout_format.RolloutFormatError, match=r"s\.json: sidecar not found"):
        rio.read_rollouts(bad)
    meta = json.loads(rollout_format.sidecar_path(small_file).read_text())
    for change, message in [
        ({"formula": "G[0,99](d >= "}, r"formula 'G\[0,99\]\(d >= ' is not valid STL"),
        ({"dt_s": -1}, r"dt_s must be a number of seconds > 0, got -1"),
        ({"n_steps": 50}, r"the sidecar says n_steps = 50 but the table holds 100"),
        ({"version": 4}, r"format version 4; this pemviz reads versions 1, 2, 3: a newer pemviz wrote the file"),
        ({"signals": {"d": "gap_m", "w": "width_m"}}, r"missing column 'width_m'"),
    ]:
        rollout_format.sidecar_path(bad).write_text(json.dumps({**meta, **change}))
        with pytest.raises(rollout_format.RolloutFormatError, match=message):
            rio.read_rollouts(bad)


def test_writer_refuses_bad_rollouts_and_leaves_no_file(tmp_path, pem):
    problem = braking_problem(pem)
    batch = problem.simulate(3, ConstantDetector(0.5), problem.target, np.random.default_rng(0))
    obs = batch.observations.copy()
    obs[1, 17, 0] = np.inf
    broken = RolloutBatch(obs, batch.detected, batch.log_p, batch.log_q, batch.observation_names)
    with pytest.raises(rollout_format.RolloutFormatError, match=r"gap_m is inf at rollout 1, step 17 \(row 117\)"):
        rollout_writer.write_rollouts(tmp_path / "x.parquet", broken, braking_meta())
    with pytest.raises(ValueError, match="must end in .parquet"):
        rollout_writer.write_rollouts(tmp_path / "x.csv", batch, braking_meta())
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(FileNotFoundError, match="rollout file .* not found"):
        rio.read_rollouts(tmp_path / "absent.parquet")
    Path(tmp_path / "junk.parquet").write_text("not parquet")
    Path(tmp_path / "junk.json").write_text(json.dumps({"formula": "G[0,99](d >= 2)", "dt_s": 0.05}))
    with pytest.raises(rollout_format.RolloutFormatError, match=r"not a Parquet file \(it starts with b'not '\)"):
        rio.read_rollouts(tmp_path / "junk.parquet")


def test_estimate_with_a_proposal_that_did_not_draw_the_file_is_refused_in_one_line(tmp_path, capsys):
    # rollouts drawn by the adaptive proposal, re-weighted as if a 50 % detector had drawn them: every detection
    # then weighs p / 0.5 ~ 2, the mean importance weight is astronomically above its expectation 1
    rollouts = tmp_path / "adaptive.parquet"
    code = cli.main(
        [
            "run",
            "--preset",
            "quick",
            "--k",
            "3",
            "--n-final",
            "60",
            "--seed",
            "1",
            "--no-record",
            "--save-rollouts",
            str(rollouts),
        ]
    )
    assert code == 0, capsys.readouterr().err
    capsys.readouterr()
    code, out, err = estimate_cli(capsys, str(rollouts), "--pem", "ml-nn", "--proposal", "naive50", "--no-record")
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 2 and len(lines) == 1, err
    assert "does not match the one that sampled the file" in lines[0] and "mean importance weight" in lines[0]
    assert out == ""
    code, out, err = estimate_cli(capsys, str(rollouts), "--no-record")  # its own log_q columns: a plausible answer
    assert code == 0, err
    # a 95 % interval, or where the weights back none their lower bound alone
    assert re.search(
        r"^mu_hat = \S+, (95% CI \[\S+, \S+\], |no 95% CI from these weights: p >= \S+ .*)ESS \S+, "
        r"k-hat \S+: (reliable|doubtful|unreliable) \(",
        out,
        re.M,
    )


def test_a_file_whose_rollouts_all_fail_with_a_mean_weight_a_little_above_one_is_plausible():
    """A run of a scene that always fails draws a mean importance weight above 1 as often as below (1.008 on a
    pedestrian scene with the brake too late): its own file was refused as drawn by another proposal. Cut at 1, it is
    an estimate of 1; a mean weight above 1000 is still refused."""
    from pemviz.commands import UsageError
    from pemviz.commands.estimate import check_plausible

    everything = estimate(np.log([1.2, 1.1, 0.9, 1.0] * 50), np.ones(200, bool), np.zeros(200))
    check_plausible(everything, "column log_q")  # no error
    assert everything.mu_hat == 1.0
    with pytest.raises(UsageError, match="does not match the one that sampled the file"):
        check_plausible(estimate(np.full(10, math.log(2000.0)), np.ones(10, bool), np.zeros(10)), "column log_q")


def test_a_run_says_how_large_its_rollout_file_will_be_before_writing_it(tmp_path, chunked, monkeypatch):
    import re

    import pemviz.sinks.rollouts as sinks

    monkeypatch.setattr(sinks, "SAY_SIZE_ABOVE_BYTES", 20_000)  # the braking's rollouts are small: 20 kB, not 100 MB
    path = tmp_path / "big.parquet"
    said: list[tuple[str, bool]] = []

    class Out:
        def write(self, text: str) -> None:
            if text.strip():
                said.append((text.strip(), path.exists()))

        def flush(self) -> None:
            pass

    sink = sinks.RolloutSink(path, stages="all", out=Out())
    Experiment(STREAMED, [sink], problem=chunked).run()
    assert len(said) == 1 and not said[0][1]  # one line, printed before the file was there
    found = re.fullmatch(
        r"--save-rollouts: big\.parquet will be about ([\d.]+) MB for the 1,150 rollouts planned, "
        r"([\d.]+) kB a rollout",
        said[0][0],
    )
    assert found, said[0][0]
    size = path.stat().st_size  # pretraining's 50 rollouts, the stage's 100 and the final 1,000
    assert abs(float(found.group(1)) * 1e6 - size) < 0.15 * size
    quiet = sinks.RolloutSink(tmp_path / "small.parquet", out=Out())
    monkeypatch.setattr(sinks, "SAY_SIZE_ABOVE_BYTES", 100 * 10**6)
    Experiment(STREAMED, [quiet], problem=chunked).run()
    assert len(said) == 1 and quiet.size_said == ""  # within 100 MB: nothing said


def test_the_size_line_counts_what_may_follow_the_stages(tmp_path):
    sink = RolloutSink(tmp_path / "r.parquet")
    sink._planned = (7_200, 1_000_000)
    assert sink.size_line(62_000, 100, 100) == (
        "--save-rollouts: r.parquet will be about 4.46 MB for the 7,200 rollouts planned, up to 624 MB if "
        "1,000,000 more follow (the retry and plain Monte Carlo), 0.62 kB a rollout"
    )
    assert sink.size_line(62_000, 10_000, 10_000) is None  # 6.2 B a rollout: 6.2 MB at most


def test_a_run_over_an_odd_re_estimates_from_its_file_to_the_runs_verdict_and_interval(tmp_path, capsys):
    """Over an ODD a failing prefix of detections is not one event (its probability also holds the parameters'
    law), so the file's re-estimate must not apply the run-drew-these-failures bound the run does not apply: the
    toy over 9 orders of magnitude (seed 0: `reliable`, 1.06e-4 to 1.18e-4, exact 1.111e-4) said `unreliable`
    from its own file before."""
    rollouts, doc = tmp_path / "odd.parquet", tmp_path / "odd.json"
    odd = "braking~choice(" + ", ".join(str(b) for b in range(5, 15)) + ")"
    flags = ["--scenario", "toy", "--param", "total=16", "--param", "safe=3", "--param", odd, "--seed", "0"]
    assert cli.main(["run", *flags, "--no-record", "--save-rollouts", str(rollouts)]) == 0
    said = capsys.readouterr().out.splitlines()
    run_line = next(line for line in said if line.startswith("mu_hat = ") and "k-hat" in line)
    assert "95% CI [1.06e-04, 1.18e-04]" in run_line and ": reliable (" in run_line, run_line
    est = run_cli("estimate", str(rollouts), "--no-record", "--json", str(doc))
    assert est.returncode == 0, est.stderr
    est_line = next(line for line in est.stdout.splitlines() if line.startswith("mu_hat = ") and "k-hat" in line)
    assert est_line == run_line
    assert json.loads(doc.read_text())["estimate"]["verdict"] == "reliable"
