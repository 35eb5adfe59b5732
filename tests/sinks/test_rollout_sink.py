"""The rollout-file sink on hand-made events: a method without importance weights is refused at the run's start, a
cancelled run leaves no file."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("pyarrow")

from pemviz.core.detectors import ConstantDetector  # noqa: E402
from pemviz.core.plan import RunPlan  # noqa: E402
from pemviz.engine.events import RolloutChunk, RunCancelled, StageStarted  # noqa: E402
from pemviz.sinks.rollouts import RolloutSink  # noqa: E402

from .synthetic import batch, run_started  # noqa: E402


def test_an_ams_run_is_refused_when_it_starts(tmp_path):
    sink = RolloutSink(tmp_path / "r.parquet")
    with pytest.raises(ValueError, match="method ams estimates without importance weights"):
        sink(run_started(method="ams", plan=RunPlan.of([(0, "ams", 30)], open_ended=True)))


def test_a_cancelled_run_leaves_no_file(tmp_path):
    path = tmp_path / "r.parquet"
    sink = RolloutSink(path)
    sink(run_started(method="mc", plan=RunPlan.of([(1, "final", 2)])))
    sink(StageStarted(1, "final", 2))
    half = ConstantDetector(0.5)
    gaps = np.array([[12.0, 8.0, 4.0, 1.5, 1.0], [12.0, 9.0, 6.0, 4.0, 3.0]])
    b = batch(gaps, ("gap_m", "ego_speed_mps", "lead_speed_mps"))
    sink(RolloutChunk(1, "final", 0, b, np.zeros(2), half, ((2, half),), half))
    assert sink._writer is not None  # the chunk went to a file being written
    sink(RunCancelled((), "cancelled by the user"))
    assert sink.written is None and list(tmp_path.iterdir()) == []
