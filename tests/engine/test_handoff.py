"""A pooled block handed to the run's process through a shared-memory file is the worker's block, bit for bit: every
array, the rows it rebuilds by replay, the draws counted; the file is gone once read, and a pool's folder with it."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
from pemviz.config import ExperimentConfig
from pemviz.engine import handoff
from pemviz.engine.executors import stream_block
from pemviz.scenarios.problems import problem_for

FIELDS = ("observations", "detected", "log_p", "log_q", "noise")


@pytest.fixture(scope="module")
def crossing_block():
    """A streamed block of 300 crossing rollouts, object rows elided (as a pooled block of the run), seed 5."""
    problem = problem_for(ExperimentConfig.of(scenario="crossing", method="mc"))
    state = np.random.default_rng(5).bit_generator.state
    return problem, stream_block(problem, 300, 0, 300, problem.target, problem.target, state, False)


def _same_block(a, b) -> None:
    (x, calls_x, k_x), (y, calls_y, k_y) = a, b
    assert (calls_x, k_x) == (calls_y, k_y) == (50, 6)  # 50 steps; 2 pedestrians x (detection + 2 errors)
    for name in FIELDS:
        u, v = getattr(x, name), getattr(y, name)
        assert u.dtype == v.dtype and u.shape == v.shape
        assert u.tobytes() == v.tobytes(), name  # the same bits
        assert v.flags.writeable
    assert x.rows_elided and y.rows_elided
    rows = np.array([0, 7, 299])
    np.testing.assert_array_equal(x.object_rows_of(rows), y.object_rows_of(rows))  # the replay travels with it


def test_a_block_handed_over_in_a_shared_file_is_the_worker_s_block_and_the_file_is_removed_once_read(
    crossing_block, tmp_path
):
    problem, block = crossing_block
    folder = handoff.make_folder(str(tmp_path))
    assert folder is not None and os.path.dirname(folder) == str(tmp_path)
    head, path, spans = packed = handoff.pack([block], folder)
    assert path is not None and os.path.dirname(path) == folder
    big = sum(getattr(block[0], name).nbytes for name in FIELDS)  # 300 x 50 x (5 + 2/8 + 1 + 1 + 4) x 8 bytes
    assert big == 300 * 50 * 8 * 11 + 300 * 50 * 2
    assert len(head) < big / 20  # the arrays are not in the pickle
    assert sum(n for _, n in spans) >= big and all(a % handoff.ALIGN == 0 for a, _ in spans)
    (back,) = handoff.unpack(packed)
    _same_block(block, back)
    assert os.listdir(folder) == []
    back[0].log_p[0, 0] = 1.0  # copy-on-write: the reader's own arrays
    with pytest.raises(OSError):
        handoff.unpack(packed)  # read once
    handoff.remove_folder(folder)
    assert not os.path.exists(folder)


def test_without_a_shared_folder_or_when_writing_there_fails_the_block_travels_in_its_pickle(crossing_block, tmp_path):
    _, block = crossing_block
    assert handoff.make_folder(str(tmp_path / "absent")) is None
    inband = handoff.pack([block], None)
    gone = str(tmp_path / "removed")  # the pool's folder removed while the worker ran
    failed = handoff.pack([block], gone)
    for head, path, spans in (inband, failed):
        assert path is None and spans == [] and len(head) > 300 * 50 * 8 * 11
        _same_block(block, handoff.unpack((head, path, spans))[0])


def test_a_pool_s_folder_removed_at_close_takes_the_blocks_never_read(crossing_block):
    _, block = crossing_block
    folder = handoff.make_folder()
    if folder is None:
        pytest.skip("no /dev/shm here: blocks travel through the pipe")
    handoff.pack([block], folder)  # a cancelled block's file
    assert len(os.listdir(folder)) == 1
    handoff.remove_folder(folder)
    assert not os.path.exists(folder)


def test_a_new_pool_s_folder_removes_those_of_runs_killed_before_they_could(tmp_path):
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    stale = tmp_path / f"{handoff.PREFIX}{int(dead.stdout)}-abc"  # a run killed with a block in flight
    stale.mkdir()
    (stale / "x.block").write_bytes(b"0" * 64)
    live = tmp_path / f"{handoff.PREFIX}{os.getpid()}-def"  # a run still going (this one)
    live.mkdir()
    other = tmp_path / "pemviz-pool-notes"  # not a pool's folder
    other.mkdir()
    folder = handoff.make_folder(str(tmp_path))
    assert folder is not None and os.path.basename(folder).startswith(f"{handoff.PREFIX}{os.getpid()}-")
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([live.name, other.name, os.path.basename(folder)])
