"""Streams that do not keep a multi-object scene's object rows (most of a cut-in batch's memory) rebuild them by replay
when read: the same bits as a stream that kept them, for the whole chunk, a selection, a concatenation and the sample
a plain Monte Carlo run shows its listeners."""

from __future__ import annotations

import numpy as np
from pemviz.config import ExperimentConfig
from pemviz.core.rollouts import RolloutBatch
from pemviz.engine.events import RolloutsSampled
from pemviz.engine.experiment import Experiment
from pemviz.scenarios.problems import problem_for

FIELDS = ("observations", "detected", "log_p", "log_q", "noise")


def cut_in_chunks(keep_rows: bool, n: int = 300, chunk: int = 128) -> list[RolloutBatch]:
    pb = problem_for(ExperimentConfig.of(scenario="cut-in"))
    return list(pb.stream(n, pb.target, pb.target, np.random.default_rng(7), chunk_size=chunk, keep_rows=keep_rows))


def test_a_stream_without_rows_rebuilds_them_bit_for_bit():
    kept, elided = cut_in_chunks(True), cut_in_chunks(False)
    assert [b.n for b in elided] == [128, 128, 44]
    for a, b in zip(kept, elided, strict=False):
        assert b.rows_elided and not a.rows_elided
        for name in FIELDS:
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
        some = np.array([0, 5, b.n - 1])
        np.testing.assert_array_equal(b.object_rows_of(some), a.objects[some])  # those three only
        assert b.rows_elided  # a selection's replay leaves the chunk without rows
        np.testing.assert_array_equal(
            b.select(b.detected[:, 40:, 1].any(axis=1)).object_rows, a.objects[a.detected[:, 40:, 1].any(axis=1)]
        )
        np.testing.assert_array_equal(b.objects, a.objects)  # read: rebuilt whole, then held
        assert not b.rows_elided and b.replay is None
    assert cut_in_chunks(False)[2].object_rows_of(np.zeros(44, bool)).shape == (0, *kept[2].objects.shape[1:])


def test_a_concatenation_and_its_selection_stay_without_rows_until_read():
    kept, elided = cut_in_chunks(True), cut_in_chunks(False)
    both = RolloutBatch.concatenate(elided)
    assert both.rows_elided and both.n == 300
    picked = both.select(np.array([3, 130, 299]))
    assert picked.rows_elided
    held = picked.with_rows()
    assert not held.rows_elided and held.replay is None
    np.testing.assert_array_equal(held.objects, RolloutBatch.concatenate(kept).objects[[3, 130, 299]])
    mixed = RolloutBatch.concatenate([elided[0], kept[1]])  # one chunk with rows: every chunk's rows, held
    assert not mixed.rows_elided
    np.testing.assert_array_equal(mixed.objects, np.concatenate([kept[0].objects, kept[1].objects]))


def test_plain_monte_carlo_shows_its_listeners_the_sample_with_its_rows():
    """``pemviz run --scenario cut-in --method mc --n 4500`` streams (above 20,000 / 5 object rows) without the rows;
    the sample of least-robust, failing and evenly spaced rollouts carries the rows the simulation saw."""
    cfg = ExperimentConfig.of(scenario="cut-in", method="mc", n_per_stage=4500, seed=3)
    pb = problem_for(cfg)
    samples: list[RolloutsSampled] = []
    Experiment(cfg, [lambda e: isinstance(e, RolloutsSampled) and samples.append(e)], problem=pb).run()
    (event,) = samples
    assert event.index is not None and not event.batch.rows_elided
    whole = RolloutBatch.concatenate(list(pb.stream(4500, pb.target, pb.target, np.random.default_rng(3))))
    np.testing.assert_array_equal(event.batch.objects, whole.objects[event.index])
    np.testing.assert_array_equal(event.batch.observations, whole.observations[event.index])


def test_a_change_of_another_field_keeps_the_rows_unbuilt():
    (chunk,) = cut_in_chunks(False, n=40, chunk=40)
    changed = chunk.with_changes(log_q=chunk.log_q * 0.0)
    assert changed.rows_elided and chunk.rows_elided and not changed.log_q.any()
    (kept,) = cut_in_chunks(True, n=40, chunk=40)
    np.testing.assert_array_equal(changed.objects, kept.objects)  # rebuilt when read, all the same
