"""A rerun recording written by a second process while the run goes on (``pemviz run --save``, the program only).

Importing rerun and logging hold the interpreter's lock, so a second process takes them off the run's path.
:class:`RecordingProcess` pickles each event to ``python -m pemviz.sinks.recording_process PATH OVERWRITE``, whose
:func:`main` hands them to a :class:`pemviz.sinks.recording.RerunSink`. :meth:`RecordingProcess.close` returns when the
file is written or raises what the sink's close raises; Ctrl-C and SIGTERM reach the run only; a run killed outright
leaves no file.

Protocol: pickled ``("event", event)`` messages on the child's standard input, then one ``("close", commit)``; the
child answers one JSON line, ``{"written": path or null}`` or ``{"error": kind, ...}``."""

from __future__ import annotations

import json
import os
import pickle
import queue
import signal
import subprocess
import sys
import tempfile
import threading
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any, cast

from pemviz.engine.events import FinalEstimate, RolloutsSampled, RunCancelled, RunStarted, StageFinished
from pemviz.engine.resources import ONE_THREAD_ENV
from pemviz.sinks import Sink

if TYPE_CHECKING:
    from pemviz.core.problems import Problem
    from pemviz.sinks.population import FailureGrouping, SharedGroups

RECORDED = (RunStarted, RolloutsSampled, StageFinished, FinalEstimate, RunCancelled)
"""The events :class:`pemviz.sinks.recording.RerunSink` takes (the others are not sent to the child)."""

CLOSE_TIMEOUT_S = 600.0
"""The most :meth:`RecordingProcess.close` waits for the child to write the file (a default run's takes ~0.1 s)."""


class RecordingProcess(Sink):
    """The listener of a run whose recording a child process writes to ``path`` (:mod:`pemviz.sinks.recording_process`).

    Args:
        path: the ``.rrd`` file; written under a temporary name and moved onto it when :meth:`close` commits.
        overwrite: replace an existing ``path`` (else :class:`pemviz.core.files.OutputExists` at :meth:`close`).

    Raises:
        OSError: the child process could not be started."""

    def __init__(self, path: str | os.PathLike, *, overwrite: bool = False) -> None:
        self.path = Path(path)
        self._errors = tempfile.TemporaryFile()
        package_root = str(Path(__file__).resolve().parents[2])
        env = {
            **os.environ,
            "PYTHONPATH": os.pathsep.join(p for p in (package_root, os.environ.get("PYTHONPATH")) if p),
            **ONE_THREAD_ENV,
        }
        self._proc = subprocess.Popen(
            [sys.executable, "-m", "pemviz.sinks.recording_process", str(self.path), "1" if overwrite else "0"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=self._errors,
            env=env,
            start_new_session=True,
        )
        self._queue: queue.SimpleQueue[bytes | None] = queue.SimpleQueue()
        self._writer = threading.Thread(target=self._write, name="pemviz-recording-feed", daemon=True)
        self._writer.start()
        self._closed = False
        self._groups: SharedGroups | None = None

    def share_failure_groups(self, groups: SharedGroups) -> None:
        """Send ``groups``' grouping of the final estimate's failures (a listener of the same run, heard before or
        after this sink) with the final estimate, rather than have the child group them again: the run groups them
        while the child logs the last stage."""
        self._groups = groups
        self._send("groups", None)

    def __call__(self, event: object) -> None:
        if self._closed or not isinstance(event, RECORDED):
            return
        self._send("event", event)
        if isinstance(event, FinalEstimate) and self._groups is not None:
            self._groups(event)  # heard once: a no-op where the run's listener has grouped them already
            self._send("grouping", self._groups.grouping)  # the child logs the rest of the estimate meanwhile

    def _send(self, kind: str, payload: object) -> None:
        """Pickle a message now (what it holds may change in place afterwards) and queue it for the writer."""
        self._queue.put(pickle.dumps((kind, payload), protocol=pickle.HIGHEST_PROTOCOL))

    def _write(self) -> None:
        """The writer thread: each pickled message to the child's input, in order; stops at ``None`` or when the
        child has gone (its input closed)."""
        pipe = self._proc.stdin
        assert pipe is not None  # started with stdin=PIPE
        try:
            while (data := self._queue.get()) is not None:
                pipe.write(data)
                pipe.flush()
        except (BrokenPipeError, OSError, ValueError):
            pass
        finally:
            try:
                pipe.close()
            except (BrokenPipeError, OSError):
                pass

    def close(self, commit: bool = True) -> Path | None:
        """Finish the recording: the child writes it (``commit``) or drops it; returns the file written, or None.

        Raises:
            pemviz.core.files.OutputExists: ``path`` appeared meanwhile and ``overwrite`` was not given.
            OSError: the file could not be written (nothing is left; an existing file is untouched), the child
                failed (its last line of errors), or it did not finish within :data:`CLOSE_TIMEOUT_S` seconds."""
        if self._closed:
            return None
        self._closed = True
        self._send("close", bool(commit))
        self._queue.put(None)
        self._writer.join()
        self._proc.stdin = None  # closed by the writer: communicate() reads the report only
        try:
            out, _ = self._proc.communicate(timeout=CLOSE_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait()
            raise OSError(
                f"the recording process did not finish within {CLOSE_TIMEOUT_S:.0f} s; nothing written "
                f"to {self.path}"
            ) from None
        report = _last_json(out)
        if not commit:  # a run that failed: its own error is the one to show
            return None
        if report is None:
            raise OSError(f"the recording process failed (exit {self._proc.returncode}): {self._last_error()}")
        return _reported(report)

    def _last_error(self) -> str:
        self._errors.seek(0)
        lines = [ln.strip() for ln in self._errors.read().decode(errors="replace").splitlines() if ln.strip()]
        return lines[-1] if lines else "no message"


def _last_json(out: bytes) -> dict | None:
    for line in reversed(out.decode(errors="replace").splitlines()):
        try:
            return json.loads(line)
        except ValueError:
            continue
    return None


def _reported(report: dict) -> Path | None:
    """The child's report as :meth:`RecordingProcess.close` returns or raises it."""
    from pemviz.core.files import OutputExists

    error = report.get("error")
    if error == "exists":
        raise OutputExists(report["message"])
    if error == "os":
        raise OSError(report.get("errno"), report.get("message"), report.get("filename"))
    if error is not None:
        raise OSError(f"the recording process failed: {report.get('message')}")
    return Path(report["written"]) if report.get("written") else None


class _GivenGroups:
    """The child's stand-in for the run's :class:`~pemviz.sinks.population.FailureGroups`: the events need no keeping
    here; at the final estimate it waits for the run's grouping, the message that follows it on ``source``."""

    problem: object = True  # "knows the run's problem": the run's groups read it
    drawing: object = None

    def __init__(self, source: _Messages) -> None:
        self.source = source
        self.grouping: FailureGrouping | None = None

    def __call__(self, event: object) -> None:
        if isinstance(event, FinalEstimate):
            message = self.source.next()
            if message[0] != "grouping":
                self.source.unread(message)
                raise ValueError(f"the run sent {message[0]!r} where the final estimate's grouping was due")
            self.grouping = message[1]


class _Messages:
    """The run's messages on standard input, one at a time, with one put back (:meth:`unread`)."""

    def __init__(self, stream: IO[bytes]) -> None:
        self.stream = stream
        self.back: list[tuple[str, Any]] = []

    def next(self) -> tuple[str, Any]:
        """The next ``(kind, payload)``; ``("end", None)`` when the run closed its side without a close message. The
        payload's type is the kind's (an event, the final estimate's grouping, the close's commit)."""
        if self.back:
            return self.back.pop()
        try:
            return pickle.load(self.stream)
        except EOFError:
            return ("end", None)

    def unread(self, message: tuple[str, Any]) -> None:
        self.back.append(message)


def _report(**fields: object) -> None:
    sys.stdout.write(json.dumps(fields) + "\n")
    sys.stdout.flush()


def main(argv: list[str] | None = None) -> int:
    """The child: read the run's events from standard input into a file recording; report on standard output.

    ``argv``: ``[PATH, OVERWRITE]`` (``"1"``: replace an existing file). Returns 0 (its outcome is in the report)."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)  # the run decides: it closes the sink, and the child then writes
    path, overwrite = (sys.argv[1:] if argv is None else argv)[:2]
    from pemviz.sinks.process import import_scipy_special_lean, settle_pyarrow_without_pandas

    import_scipy_special_lean()  # before the engine's and the sink's modules import it
    from pemviz.core.files import OutputExists
    from pemviz.engine.experiment import RobustnessByMetric
    from pemviz.sinks.recording import RerunSink

    settle_pyarrow_without_pandas()
    sink = RerunSink.to_file(path, overwrite=overwrite == "1")
    source = _Messages(sys.stdin.buffer)
    given = _GivenGroups(source)
    failed: str | None = None
    commit: bool | None = None
    while True:
        kind, payload = source.next()
        if kind == "end":
            break
        if kind == "close":
            commit = payload
            break
        if kind == "groups":
            sink.share_failure_groups(given)
            continue
        if failed is not None:
            continue  # keep reading, so that the run never blocks on a full pipe
        try:
            if isinstance(payload, RunStarted):
                from pemviz.scenarios.registry import problem_for  # any registered scenario

                sink.problem = problem_for(payload.config)
            if isinstance(payload, RolloutsSampled) and isinstance(payload.robustness_by_metric, RobustnessByMetric):
                payload.robustness_by_metric.problem = cast("Problem", sink.problem)  # problem_for's, set at RunStarted
            sink(payload)
        except Exception as exc:  # reported at close: the run's own estimate is unaffected
            failed = f"{type(exc).__name__}: {exc}"
    if commit is None:  # the run ended without closing (killed): nothing is written, as in one process
        return 0
    if failed is not None:
        sink.close(commit=False)
        _report(error="failed", message=failed)
        return 0
    try:
        where = sink.close(commit=commit)
    except OutputExists as exc:
        _report(error="exists", message=str(exc))
    except OSError as exc:
        _report(error="os", errno=exc.errno, message=exc.strerror or str(exc), filename=exc.filename)
    else:
        _report(written=str(where) if where is not None else None)
    return 0


if __name__ == "__main__":
    main()
    os._exit(0)  # reported and written: nothing left for the interpreter's shutdown but rerun's threads (~0.1 s)
