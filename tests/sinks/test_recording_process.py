"""The program's recording written by a second process (:mod:`pemviz.sinks.recording_process`): the same recording
as the one-process sink writes, rerun never imported by the run itself, and the sink's promises (errors, no file
without a commit, an existing file kept) across the two processes."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

rr = pytest.importorskip("rerun")
pytest.importorskip("datafusion", reason="rerun-sdk[catalog] reads recordings back")

from pemviz import cli  # noqa: E402
from pemviz.core.files import OutputExists  # noqa: E402
from pemviz.sinks import HANDLERS, Sink  # noqa: E402
from pemviz.sinks.recording import RerunSink  # noqa: E402
from pemviz.sinks.recording_process import RECORDED, RecordingProcess  # noqa: E402

from conftest import REPO, verify_rrd  # noqa: E402

RUN = ["run", "--preset", "quick", "--k", "2", "--n", "30", "--n-final", "40", "--ce-epochs", "5", "--seed", "3"]
OWN = ("rerun_segment_id", "wall_s", "Markdown", "TextDocument")
"""Columns that differ between two runs by what they are: the recording's id, and the run's wall time (seconds, and
the description's and estimate's text that states it)."""


def program(*args: str, cwd: Path, importtime: bool = False) -> subprocess.CompletedProcess:
    env = {**os.environ, "RERUN_ANALYTICS": "false", "PYTHONPATH": str(REPO)}
    flags = ["-X", "importtime"] if importtime else []
    return subprocess.run(
        [sys.executable, *flags, "-m", "pemviz.cli", *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )


def tables(path: Path) -> dict:
    with rr.server.Server(datasets={"run": [str(path)]}) as server:
        ds = server.client().get_dataset("run")
        return {index: ds.reader(index=index).to_arrow_table() for index in (None, "step", "stage")}


@pytest.fixture(scope="module")
def the_program(tmp_path_factory) -> tuple[subprocess.CompletedProcess, Path]:
    """``pemviz run RUN --save child.rrd`` as the program, run once with Python's import listing (``-X importtime``,
    which changes nothing the run writes): its process and its recording."""
    cwd = tmp_path_factory.mktemp("program")
    proc = program(*RUN, "--save", "child.rrd", cwd=cwd, importtime=True)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return proc, cwd / "child.rrd"


def test_the_programs_recording_equals_the_one_process_recording(the_program, tmp_path, capsys):
    """``pemviz run --save`` as the program (a child process records) and as a library call (the sink in the run's
    process): the same entities and components, every value equal but the wall times, and rerun's checker accepts
    both."""
    _, child_rrd = the_program
    assert cli.main([*RUN, "--save", str(tmp_path / "inproc.rrd")]) == 0
    capsys.readouterr()
    for path in (child_rrd, tmp_path / "inproc.rrd"):
        verify_rrd(path)
    child, inproc = tables(child_rrd), tables(tmp_path / "inproc.rrd")
    compared = 0
    for index in child:
        a, b = child[index], inproc[index]
        assert sorted(a.column_names) == sorted(b.column_names), index
        assert a.num_rows == b.num_rows, index
        for name in a.column_names:
            if any(word in name for word in OWN):
                continue
            assert repr(a.column(name).to_pylist()) == repr(b.column(name).to_pylist()), (index, name)  # nan == nan
            compared += 1
    assert compared > 100  # the bulk of the recording: traces, stage series, histograms, the final estimate
    stage = child["stage"]
    mu = [v for v in stage.column("/stages/log10_mu_hat:Scalars:scalars").to_pylist() if v is not None]
    assert len(mu) >= 2 and np.isfinite(mu[-1][0])  # stages with failures: an estimate each


def test_the_run_itself_never_imports_rerun(the_program):
    """The run's process: no rerun, no pyarrow (the child imports both); the recording is written all the same."""
    proc, rrd = the_program
    imported = {line.split("|")[-1].strip() for line in proc.stderr.splitlines() if line.startswith("import time:")}
    assert "pemviz.engine.experiment" in imported  # the listing is the run's own
    assert not {"rerun", "pyarrow", "pemviz.sinks.recording"} & imported
    assert rrd.stat().st_size > 10_000


def test_the_child_is_sent_the_events_the_rerun_sink_takes():
    """:data:`RECORDED` is exactly the events whose handler :class:`RerunSink` overrides (the others are not sent)."""
    taken = {kind for kind, method in HANDLERS.items() if getattr(RerunSink, method) is not getattr(Sink, method)}
    assert taken == set(RECORDED)


def test_close_without_commit_writes_nothing_and_keeps_an_existing_file(tmp_path):
    old = tmp_path / "old.rrd"
    old.write_bytes(b"RRF2 old")
    sink = RecordingProcess(old, overwrite=True)
    assert sink.close(commit=False) is None
    assert old.read_bytes() == b"RRF2 old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old.rrd"]
    assert sink.close() is None  # twice: harmless


def test_a_file_that_appeared_meanwhile_is_not_replaced(tmp_path):
    path = tmp_path / "r.rrd"
    sink = RecordingProcess(path)
    path.write_bytes(b"someone else's")
    with pytest.raises(OutputExists):
        sink.close()
    assert path.read_bytes() == b"someone else's"


def test_a_folder_that_went_away_is_an_os_error_naming_the_cause(tmp_path):
    sink = RecordingProcess(tmp_path / "gone" / "r.rrd")
    with pytest.raises(OSError) as info:
        sink.close()
    assert "No such file" in str(info.value)


def test_a_child_that_fails_on_an_event_is_reported_and_writes_nothing(tmp_path):
    from pemviz.engine.events import StageFinished

    sink = RecordingProcess(tmp_path / "r.rrd")
    sink(StageFinished(result=None))  # a stage before the run started: the child's sink fails on it
    with pytest.raises(OSError, match="the recording process failed: "):
        sink.close()
    assert list(tmp_path.iterdir()) == []


def test_a_run_that_ends_without_closing_leaves_no_file(tmp_path):
    """The run killed outright: the child's input ends without a close, and it writes nothing."""
    sink = RecordingProcess(tmp_path / "r.rrd")
    sink._queue.put(None)  # the writer closes the child's input, as the run's death would
    sink._writer.join()
    assert sink._proc.wait(timeout=120) == 0
    assert list(tmp_path.iterdir()) == []
