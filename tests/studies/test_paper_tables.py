"""pemviz.studies.paper_tables: rows of the paper's Tables II and III from run records."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pemviz.settings import METRICS
from pemviz.studies.paper_tables import (
    RowSpec,
    log_mean_and_se,
    markdown,
    row_specs,
    rows_csv,
    summarise_row,
    tables_rows,
)
from pemviz.studies.validation import RunRecord


def test_log_mean_and_se_equal_numpy_and_stay_exact_below_float_range():
    x = np.array([1e-15, 3e-15, 2e-15, 6e-15])
    lm, lse = log_mean_and_se(np.log(x))
    assert math.exp(lm) == pytest.approx(x.mean(), rel=1e-12)
    assert math.exp(lse) == pytest.approx(x.std(ddof=1) / 2.0, rel=1e-12)
    lm, lse = log_mean_and_se(np.log(x) - 1000.0)  # 1e-450: no float64 holds it, the logs do
    assert lm == pytest.approx(math.log(x.mean()) - 1000.0, abs=1e-12)
    assert log_mean_and_se([-math.inf, -math.inf]) == (-math.inf, -math.inf)


def _record(label: str, seed: int, mu: float, failures: int) -> RunRecord:
    return RunRecord(
        "toy",
        label,
        seed,
        math.log(mu),
        failures,
        100,
        3.0,
        20.0,
        19.0,
        100,
        1.0,
        log_ci_lo=math.log(mu / 2),
        log_ci_hi=math.log(mu * 2),
    )


def test_a_row_is_the_mean_and_standard_error_over_repetitions():
    spec = RowSpec("II", "MC_100", (("method", "mc"),))
    row = summarise_row(spec, [_record("MC_100", 0, 1e-3, 1), _record("MC_100", 1, 3e-3, 3)], math.log(1e-3))
    assert math.exp(row.log_mean) == pytest.approx(2e-3, rel=1e-12)
    assert math.exp(row.log_se) == pytest.approx(np.std([1e-3, 3e-3], ddof=1) / math.sqrt(2), rel=1e-12)
    assert (row.reps, row.mean_failures, row.covered) == (2, 2.0, 1)  # 3e-3 / 2 > 1e-3
    assert "| MC_100 | 2.000e-03 (+-1.00e-03) | 2.0/100 | 20.0 | 19.0 | 3.0 | 1.0000e-03 | 2 | 1/2 |" in markdown(
        [row], "II"
    )
    assert rows_csv([row]).splitlines()[1].startswith("II,MC_100,2,")


def test_table_three_starts_with_the_classic_row_of_table_two():
    specs = row_specs({"n_per_stage": 100}, [], mc_large=1000, naive_large=300)
    labels = [s.label for s in specs]
    assert labels[:6] == ["MC_100", "MC_1000", "naive-50_100", "naive-50_300", "adaptive_100", "AMS_2100"]
    assert labels[6:] == [f"r_{m}" for m in METRICS if m != "classic"]
    records = {s.label: [_record(s.label, k, 1e-3 * (i + 1), 1) for k in range(2)] for i, s in enumerate(specs)}
    rows = tables_rows(specs, records, math.log(1e-3), [])
    (classic,) = [r for r in rows if r.label == "r_classic"]
    (adaptive,) = [r for r in rows if r.label == "adaptive_100"]
    assert classic.table == "III" and classic.log_mean == adaptive.log_mean
    assert [r.table for r in rows] == ["II"] * 6 + ["III"] * len(METRICS)
