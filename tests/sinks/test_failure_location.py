"""Where each failure of an estimate lies in the kept batches (pemviz.sinks.population.locate_rows), against a
dictionary built rollout by rollout."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from pemviz.core.population import FailureShares
from pemviz.sinks.population import locate_rows


def _by_dict(stage: np.ndarray, index: np.ndarray, sampled: dict) -> list[int]:
    rows_of = {}
    for s, event in sampled.items():
        numbers = range(event.batch.n) if event.index is None else event.index.tolist()
        rows_of[s] = {k: r for r, k in enumerate(numbers)}  # a number kept twice: its last row
    return [rows_of.get(s, {}).get(i, -1) for s, i in zip(stage.tolist(), index.tolist(), strict=False)]


def test_each_failure_s_row_is_the_one_a_dictionary_of_the_kept_rollouts_gives():
    rng = np.random.default_rng(3)
    n = 500
    sample = rng.permutation(n)[:120]
    sample[7] = sample[80]  # a number kept twice: the later row
    sampled = {
        1: SimpleNamespace(index=None, batch=SimpleNamespace(n=n)),  # a whole stage
        2: SimpleNamespace(index=sample, batch=SimpleNamespace(n=sample.size)),  # a streamed stage's sample
        4: SimpleNamespace(index=np.zeros(0, np.int64), batch=SimpleNamespace(n=0)),  # kept nothing
    }
    stage = rng.choice([1, 2, 3, 4], size=2000)
    index = rng.integers(0, n + 5, size=2000)  # some beyond the stage's rollouts
    index[:40] = sample[80]
    stage[:40] = 2
    zeros = np.zeros(stage.size)
    shares = FailureShares(stage, index, zeros, zeros, zeros)
    rows = locate_rows(shares, sampled)  # type: ignore[arg-type]
    want = _by_dict(stage, index, sampled)
    assert rows.dtype == np.int64 and rows.tolist() == want
    assert rows[:40].tolist() == [80] * 40
    assert 100 < (rows >= 0).sum() < 2000 and (rows[stage == 3] == -1).all() and (rows[stage == 4] == -1).all()
    assert (rows[(stage == 1) & (index < n)] == index[(stage == 1) & (index < n)]).all()
    assert locate_rows(FailureShares(*(np.zeros(0),) * 5), sampled).tolist() == []  # type: ignore[arg-type]
