"""Rollout files whose ``log_p`` holds -inf: an action the PEM cannot take (a 50 % sampler detecting a car the camera
cannot see), whose rollout has importance weight 0. Such files are written and read back bit for bit; NaN or +inf in
``log_p``, and any non-finite ``log_q``, are refused in one line naming the column, rollout and step; a cut-in naive50
run re-estimates from its file to its own numbers."""

from __future__ import annotations

import json
import math
import re
import tempfile
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pemviz import cli
from pemviz.core.rollouts import RolloutBatch
from pemviz.io import rollout_format, rollout_writer
from pemviz.io import rollouts as rio
from pemviz.io.rollout_estimate import REESTIMATE_RTOL, estimate_rollouts

from conftest import estimated_log_mu

META = rollout_format.RolloutMeta(formula="G[0,5](d >= 2)", dt_s=0.1)
"""A sidecar for the hand-written batches: one signal, the gap (metres), T = 6 steps."""


def batch_of(log_p: np.ndarray, log_q: np.ndarray | None = None) -> RolloutBatch:
    """N rollouts of T steps [N, T] with the given log-probabilities (nats; log_q default log 0.5), gaps 5 .. 1 m and
    a detection at every other step."""
    n, t = log_p.shape
    gap = np.tile(np.linspace(5.0, 1.0, t), (n, 1))[..., None]
    detected = (np.arange(n * t).reshape(n, t, 1) % 2).astype(bool)
    log_q = np.full((n, t), math.log(0.5)) if log_q is None else log_q
    return RolloutBatch(gap, detected, log_p, log_q, ("gap_m",))


def with_impossible_actions() -> RolloutBatch:
    """4 rollouts x 6 steps: rollout 1 has an impossible action at step 2, rollout 3 at steps 0 and 5."""
    log_p = np.log(np.linspace(0.05, 0.95, 24)).reshape(4, 6)
    log_p[1, 2] = log_p[3, 0] = log_p[3, 5] = -np.inf
    return batch_of(log_p)


def test_neg_inf_log_p_is_written_and_read_back_bit_for_bit_and_weighs_zero(tmp_path):
    batch = with_impossible_actions()
    path = rollout_writer.write_rollouts(tmp_path / "r.parquet", batch, META)
    data = rio.read_rollouts(path)
    assert data.log_p.tobytes() == batch.log_p.tobytes() and data.log_q.tobytes() == batch.log_q.tobytes()
    assert np.isneginf(data.log_p).sum() == 3
    log_w = data.log_weight()  # the first T - 1 = 5 steps: rollout 3's step 5 is not among them
    assert np.isneginf(log_w).tolist() == [False, True, False, True]
    assert np.isfinite(log_w[[0, 2]]).all()


BAD = {
    "log_p-nan": (
        "log_p",
        math.nan,
        r"log_p is NaN at rollout 2, step 3 \(row 15\); values must be finite numbers "
        r"or -inf \(an action the PEM cannot take: weight 0\)$",
    ),
    "log_p-inf": (
        "log_p",
        math.inf,
        r"log_p is inf at rollout 2, step 3 \(row 15\); values must be finite numbers " r"or -inf",
    ),
    "log_q-neg-inf": (
        "log_q",
        -math.inf,
        r"log_q is -inf at rollout 2, step 3 \(row 15\); values must be finite "
        r"numbers \(a proposal drew each action: q > 0\)$",
    ),
    "log_q-nan": ("log_q", math.nan, r"log_q is NaN at rollout 2, step 3 \(row 15\); values must be finite numbers"),
    "log_q-inf": ("log_q", math.inf, r"log_q is inf at rollout 2, step 3 \(row 15\); values must be finite numbers"),
}


def one_line(exc: pytest.ExceptionInfo) -> str:
    msg = str(exc.value)
    assert "\n" not in msg
    return msg


@pytest.mark.parametrize("case", list(BAD))
def test_the_writer_refuses_nan_or_inf_log_p_and_non_finite_log_q_naming_rollout_and_step(case, tmp_path):
    column, value, message = BAD[case]
    batch = with_impossible_actions()  # the -inf of log_p elsewhere are allowed
    arrays = {"log_p": batch.log_p.copy(), "log_q": batch.log_q.copy()}
    arrays[column][2, 3] = value
    path = tmp_path / "r.parquet"
    with pytest.raises(rollout_format.RolloutFormatError, match=message) as exc:
        rollout_writer.write_rollouts(path, batch_of(arrays["log_p"], arrays["log_q"]), META)
    assert one_line(exc).startswith(f"{path} (not written): ")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("case", list(BAD))
def test_the_reader_refuses_nan_or_inf_log_p_and_non_finite_log_q_naming_rollout_and_step(case, tmp_path, capsys):
    column, value, message = BAD[case]
    good = rollout_writer.write_rollouts(tmp_path / "good.parquet", with_impossible_actions(), META)
    table = pq.read_table(good)
    x = table.column(column).to_numpy().copy()
    x[2 * 6 + 3] = value
    bad = tmp_path / "bad.parquet"
    pq.write_table(table.set_column(table.column_names.index(column), column, pa.array(x)), bad)
    side = json.loads(rollout_format.sidecar_path(good).read_text())
    side.pop("table_sha256")
    rollout_format.sidecar_path(bad).write_text(json.dumps(side))
    with pytest.raises(rollout_format.RolloutFormatError, match=message) as exc:
        rio.read_rollouts(bad)
    assert one_line(exc).startswith(f"{bad}: ")
    code = cli.main(["estimate", str(bad), "--no-record"])
    out = capsys.readouterr()
    assert code == 2 and out.out == "" and len(out.err.strip().splitlines()) == 1
    assert out.err.startswith(f"pemviz estimate: error: {bad}: ") and re.search(message.rstrip("$"), out.err)


# ------------------------------------------------------------------------------------------ property tests

LOG_P = st.one_of(st.just(-math.inf), st.floats(-1e300, 0.0, allow_nan=False))
"""A step's log p (nats): any number <= 0 (-0.0 too), or -inf (an action the PEM cannot take)."""


@st.composite
def log_p_arrays(draw: st.DrawFn) -> np.ndarray:
    n, t = draw(st.integers(1, 4)), draw(st.integers(2, 5))
    return np.array(draw(st.lists(LOG_P, min_size=n * t, max_size=n * t)), dtype=np.float64).reshape(n, t)


@settings(max_examples=60, deadline=None)
@given(log_p_arrays())
def test_any_log_p_of_numbers_at_most_0_and_neg_inf_reads_back_bit_for_bit(log_p):
    batch = batch_of(log_p)
    with tempfile.TemporaryDirectory() as folder:
        data = rio.read_rollouts(rollout_writer.write_rollouts(Path(folder) / "r.parquet", batch, META))
    assert data.log_p.tobytes() == log_p.tobytes() and data.log_q.tobytes() == batch.log_q.tobytes()


@settings(max_examples=60, deadline=None)
@given(log_p_arrays(), st.data())
def test_the_first_nan_or_inf_in_log_p_is_named_by_rollout_and_step(log_p, data):
    n, t = log_p.shape
    rows = data.draw(st.lists(st.integers(0, n * t - 1), min_size=1, max_size=3, unique=True))
    values = data.draw(st.lists(st.sampled_from([math.nan, math.inf]), min_size=len(rows), max_size=len(rows)))
    log_p = log_p.copy().reshape(-1)
    log_p[rows] = values
    first = min(rows)
    what = "NaN" if math.isnan(log_p[first]) else "inf"
    message = f"log_p is {what} at rollout {first // t}, step {first % t} (row {first}); values must be finite"
    with tempfile.TemporaryDirectory() as folder:
        with pytest.raises(rollout_format.RolloutFormatError) as exc:
            rollout_writer.write_rollouts(Path(folder) / "r.parquet", batch_of(log_p.reshape(n, t)), META)
        assert message in one_line(exc) and not any(Path(folder).iterdir())


# ------------------------------------------------------------------------------------------ a cut-in run


def same(a: float, b: float) -> bool:
    return a == b or (math.isnan(a) and math.isnan(b))


def final_row(out: str) -> str:
    """failures .. verdict of the ``final`` row of a run's or an estimate's table."""
    line = next(ln for ln in out.splitlines() if ln.startswith("  final "))
    cells = line.split("   <-")[0].split()
    return " ".join(cells[cells.index(next(c for c in cells if "/" in c)) :][:8])


@pytest.mark.parametrize("scenario, n", [("cut-in", 200), ("cut-in-rare", 100)])
def test_a_cut_in_naive50_run_re_estimates_from_its_file_to_its_own_numbers(scenario, n, tmp_path, capsys):
    """naive50 detects cars the camera cannot see: the file holds their -inf log p, and its weights of 0 give the
    run's log mu_hat (to 1e-9), failures, ESS and verdict (cut-in-rare: every failure has weight 0, mu_hat = 0)."""
    path = tmp_path / "r.parquet"
    args = [
        "run",
        "--scenario",
        scenario,
        "--method",
        "naive50",
        "--n",
        str(n),
        "--n-final",
        str(n),
        "--seed",
        "0",
        "--no-record",
        "--save-rollouts",
        str(path),
    ]
    assert cli.main(args) == 0, capsys.readouterr().err
    run = capsys.readouterr().out
    data = rio.read_rollouts(path)
    said = data.meta.provenance["estimate"]
    assert np.isneginf(data.log_p).any() and np.isfinite(data.log_q).all()
    cap = said.get("verdict_cap")
    again = estimate_rollouts(
        data,
        data.log_p,
        data.log_q,
        weights=data.meta.weights or "to-failure",
        log_p_seen=said.get("log_p_seen"),
        verdict_cap=tuple(cap) if cap else None,
    )
    assert np.isneginf(again.log_weight).any()  # weight 0, not an error
    est = again.estimate
    run_log_mu = float(said["log_mu_hat"])  # "-inf" in JSON when every failure weighs 0
    assert est.log_mu_hat == run_log_mu or abs(math.expm1(est.log_mu_hat - run_log_mu)) <= REESTIMATE_RTOL
    assert (est.n, est.n_failures, est.verdict) == (said["n"], said["n_failures"], said["verdict"])
    assert same(est.ess, float(said["ess"]))
    if scenario == "cut-in-rare":
        assert est.log_mu_hat == -math.inf and est.n_failures > 0 and np.isneginf(again.log_weight[again.failed]).all()
    doc = tmp_path / "estimate.json"
    assert cli.main(["estimate", str(path), "--no-record", "--json", str(doc)]) == 0
    out = capsys.readouterr()
    assert out.err == f"result: {doc}\n" and "warning" not in out.out
    assert final_row(out.out) == final_row(run)
    assert estimated_log_mu(doc) == est.log_mu_hat  # bit for bit, -inf included
    assert "mean importance weight" in out.out and " nan " not in out.out


def test_a_file_whose_every_weight_is_0_checks_a_mean_weight_of_0(tmp_path):
    log_p = np.log(np.full((3, 6), 0.5))
    log_p[:, 1] = -np.inf
    data = rio.read_rollouts(rollout_writer.write_rollouts(tmp_path / "r.parquet", batch_of(log_p), META))
    check = estimate_rollouts(data, data.log_p, data.log_q).check
    assert (check.log_mean, check.se, check.n, check.far) == (-math.inf, 0.0, 3, False)
