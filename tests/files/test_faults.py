"""Faults, interrupts and hostile input: nothing lost, nothing hangs.

Groups (the test names start with them; ``scripts/hostile_cases.py`` counts them): ``test_signal_*`` SIGINT /
SIGTERM / SIGKILL at seeded random points of ``run`` (with ``--save`` and ``--save-rollouts``) and ``estimate``;
``test_disk_*`` a full disk (RLIMIT_FSIZE); ``test_concurrent_*`` writers to one path; ``test_sidecar_*`` hostile
sidecars; ``test_cli_*`` the command-line reproductions; ``test_writer_*`` the file-writing primitives.

The signal tests assert what holds whatever the timing: the old file is intact or the new complete one is there,
a rollout unit is read whole or reported incomplete, and after SIGINT / SIGTERM no temporary file remains.
``FAULT_SEEDS`` (default 1) random points per signal.
"""

from __future__ import annotations

import json
import os
import random
import resource
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from pemviz import cli
from pemviz.core.files import OutputExists, atomic_write
from pemviz.core.rollouts import RolloutBatch
from pemviz.io import rollout_format, rollout_writer
from pemviz.io import rollouts as rio
from pemviz.io.files import check_output_path
from pemviz.io.rollout_sidecars import braking_meta

from conftest import REPO, verify_rrd

FAULT_SEEDS = range(int(os.environ.get("FAULT_SEEDS", "1")))
SMALL_RUN = ["run", "--preset", "quick", "--k", "1", "--n", "10", "--n-final", "10", "--ce-epochs", "1"]
OLD_RRD = b"RRF2" + b"old recording" * 10


def cli_line(capsys, *args: str) -> tuple[int, str]:
    try:
        code = cli.main(list(args))
    except SystemExit as exc:  # argparse's own errors (a wrong type) exit from the parser
        code = exc.code
    err = capsys.readouterr().err.strip()
    return code, err


def leftovers(folder: Path) -> list[str]:
    """Temporary files of pemviz writers (``.NAME.XXXXXXXX.tmp``) and probe files in ``folder``."""
    return sorted(p.name for p in folder.iterdir() if p.name.endswith(".tmp") or p.name.startswith(".pemviz-probe"))


def small_batch(n: int = 4, t: int = 6, seed: int = 0) -> RolloutBatch:
    rng = np.random.default_rng(seed)
    gap = np.linspace(20.0, 1.0, t)[None, :] + rng.uniform(0, 1, (n, 1))
    obs = np.stack([gap, np.full((n, t), 10.0), np.zeros((n, t))], axis=-1)
    # log_q = log_p: rollouts of the target itself, weights 1, so that ``pemviz estimate`` on the unit finishes with
    # exit code 0 when no signal stops it (a mean weight far from 1 is an error, exit 2)
    return RolloutBatch(
        obs,
        rng.uniform(size=(n, t)) < 0.5,
        np.full((n, t), -0.1),
        np.full((n, t), -0.1),
        ("gap_m", "ego_speed_mps", "lead_speed_mps"),
    )


def write_unit(path: Path, seed: int = 0) -> None:
    batch = small_batch(seed=seed)
    rollout_writer.write_rollouts(path, batch, braking_meta(formula="G[0,5](d >= 2)"), overwrite=True)


def spawn(args: list[str], cwd: Path, **kw) -> subprocess.Popen:
    env = {**os.environ, "RERUN_ANALYTICS": "false", "PYTHONPATH": str(REPO)}
    return subprocess.Popen(
        [sys.executable, "-m", "pemviz.cli", *args],
        cwd=cwd,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        **kw,
    )


def unit_state(path: Path) -> str:
    """``complete`` (reads), ``incomplete`` (the reader says the unit was cut short) for a rollout unit."""
    try:
        rio.read_rollouts(path)
    except rollout_format.RolloutFormatError as exc:
        assert "interrupted or concurrent write" in str(exc), exc
        return "incomplete"
    return "complete"


# ------------------------------------------------------------------------------------------------ signals


def wait_until_pemviz_handles_sigterm(pid: int, timeout_s: float = 60.0) -> None:
    """Wait until ``pemviz.cli.main`` runs in ``pid`` (its SIGTERM handler shows in /proc's SigCgt mask): a
    signal before that meets the bare interpreter starting up, not pemviz."""
    status = Path(f"/proc/{pid}/status")
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            caught = next(ln for ln in status.read_text().splitlines() if ln.startswith("SigCgt:"))
        except (OSError, StopIteration):
            return  # gone already, or no /proc: start the clock now
        if int(caught.split()[1], 16) >> (signal.SIGTERM - 1) & 1:
            return
        time.sleep(0.01)


def kill_at_random_point(proc: subprocess.Popen, sig: int, seed: int, latest_s: float) -> tuple[int, str]:
    """``sig`` at a point drawn from ``seed`` in [0, latest_s] seconds after pemviz took over the process."""
    wait_until_pemviz_handles_sigterm(proc.pid)
    time.sleep(random.Random(seed).uniform(0.0, latest_s))
    if proc.poll() is None:
        proc.send_signal(sig)
    try:
        _, err = proc.communicate(timeout=120)  # a signal never leaves a hang
    except subprocess.TimeoutExpired:
        proc.kill()
        raise AssertionError(f"still running 120 s after signal {sig}") from None
    return proc.returncode, err


@pytest.mark.parametrize("seed", FAULT_SEEDS)
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM, signal.SIGKILL], ids=["INT", "TERM", "KILL"])
def test_signal_at_a_random_point_of_run_keeps_old_files_or_leaves_complete_new_ones(tmp_path, sig, seed):
    rrd, parquet = tmp_path / "f.rrd", tmp_path / "x.parquet"
    rrd.write_bytes(OLD_RRD)
    write_unit(parquet)
    old_unit = {p: p.read_bytes() for p in (parquet, rollout_format.sidecar_path(parquet))}
    proc = spawn([*SMALL_RUN, "--save", rrd.name, "--save-rollouts", parquet.name, "--overwrite"], tmp_path)
    code, err = kill_at_random_point(proc, sig, 1000 * int(sig) + seed, latest_s=10.0)
    lines = [ln for ln in err.splitlines() if "Traceback" in ln]
    assert not lines, err[-3000:]
    if rrd.read_bytes() != OLD_RRD:
        verify_rrd(rrd)  # replaced only by a complete recording
    state = unit_state(parquet)
    if state == "complete" and {p: p.read_bytes() for p in old_unit} != old_unit:
        n = rio.read_rollouts(parquet).n
        if code in (0, -signal.SIGKILL) or "the run finished" in err:
            assert n == 10, err[-2000:]  # the new unit, whole (also when the signal came after the last stage)
        else:  # interrupted after a stage finished: the run kept it, and said so
            assert n > 0 and f"rollouts {parquet.name} kept: stage" in err, err[-2000:]
    if sig == signal.SIGKILL:
        assert code == -signal.SIGKILL or code == 0
        return
    # -2: the interpreter reports a Ctrl-C by ending on SIGINT (a shell shows 130)
    assert code in (0, 130, 143, -signal.SIGINT), err[-2000:]
    assert leftovers(tmp_path) == []
    if code != 0:
        last = err.strip().splitlines()[-1]
        how = "Ctrl-C" if sig == signal.SIGINT else "SIGTERM"  # "pemviz:" when it came while parsing the flags
        assert last.startswith((f"pemviz run: interrupted ({how})", f"pemviz: interrupted ({how})")), last
        assert state == "complete"  # the run ended before the unit was committed: the old one is whole


@pytest.mark.parametrize("seed", FAULT_SEEDS)
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM, signal.SIGKILL], ids=["INT", "TERM", "KILL"])
def test_signal_at_a_random_point_of_estimate_keeps_the_old_recording_or_writes_a_complete_one(tmp_path, sig, seed):
    write_unit(tmp_path / "x.parquet")
    rrd = tmp_path / "e.rrd"
    rrd.write_bytes(OLD_RRD)
    proc = spawn(["estimate", "x.parquet", "--save", rrd.name, "--overwrite"], tmp_path)
    code, err = kill_at_random_point(proc, sig, 2000 * int(sig) + seed, latest_s=5.0)
    assert "Traceback" not in err, err[-3000:]
    if rrd.read_bytes() != OLD_RRD:
        verify_rrd(rrd)
    if sig != signal.SIGKILL:
        assert code in (0, 130, 143, -signal.SIGINT), err[-2000:]  # as for run
        assert leftovers(tmp_path) == []


def terminate_after_stage_1(monkeypatch, stage: int = 1) -> None:
    """The engine of the next run raises :class:`pemviz.commands.Terminated` (as the SIGTERM handler does) once its
    stage 1 (or ``stage``) has finished."""
    from pemviz.commands import Terminated
    from pemviz.engine import experiment as engine
    from pemviz.engine.events import StageFinished

    class TerminatedAfterStage1(engine.Experiment):
        def __init__(self, config, listeners=(), cancel=None, *, problem):
            def term(event):
                if isinstance(event, StageFinished) and event.result.stage == stage:
                    raise Terminated

            super().__init__(config, [*listeners, term], cancel, problem=problem)

    monkeypatch.setattr(engine, "Experiment", TerminatedAfterStage1)


def test_signal_sigterm_mid_run_finishes_the_recording_in_process(tmp_path, capsys, monkeypatch):
    """SIGTERM raised inside the engine (as the handler raises it): one line, exit 143, a recording that
    verifies and is marked interrupted, nothing else in the folder."""
    terminate_after_stage_1(monkeypatch)
    code, err = cli_line(capsys, *SMALL_RUN, "--k", "3", "--save", str(tmp_path / "t.rrd"))
    assert code == 143
    assert err.splitlines()[-1] == (
        "pemviz run: interrupted (SIGTERM); 2 stage(s) finished; recording "
        f"{tmp_path / 't.rrd'} (marked interrupted)"
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["t.rrd"]
    verify_rrd(tmp_path / "t.rrd")


def test_sigterm_mid_run_keeps_the_finished_stage_s_rollouts_and_names_the_outputs_it_did_not_write(
    tmp_path, capsys, monkeypatch
):
    """SIGTERM inside the stages of a run asked for a rollout file and result files: the rollout file keeps the last
    finished stage (CE stage 1; pretraining is never saved), whole and committed, and ``pemviz estimate`` gives back
    the estimate its row printed; the line says so, and names each result file not written, with its flag, none of
    which exists (a run interrupted there used to keep no rollouts at all)."""
    terminate_after_stage_1(monkeypatch)
    monkeypatch.chdir(tmp_path)
    code, err = cli_line(
        capsys,
        *SMALL_RUN,
        "--k",
        "3",
        "--no-record",
        "--save-rollouts",
        "r.parquet",
        "--json",
        "r.json",
        "--report",
        "r.html",
    )
    assert code == 143
    last = err.splitlines()[-1]
    assert last.startswith("pemviz run: interrupted (SIGTERM); 2 stage(s) finished; rollouts r.parquet kept: stage 1, ")
    assert last.endswith(
        "its row's estimate; pemviz estimate gives it back); not written: r.json (--json), r.html (--report)"
    )
    assert leftovers(tmp_path) == []
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.parquet", "r.rollouts.json"]
    assert "stage 1, the last finished, 10 rollouts (no failure, its row's estimate" in last
    assert cli.main(["estimate", "r.parquet", "--no-record"]) == 0
    assert "final                0/10           0 " in capsys.readouterr().out  # stage 1's 10 rollouts, no failure


def test_an_interrupted_run_s_rollout_file_re_estimates_to_the_kept_stage_s_row(tmp_path, capsys, monkeypatch):
    """SIGTERM once the final batch (stage 2 of --k 1, seed 0: 1 failure in 10) has finished, before the run's
    estimate: the file keeps that batch, and pemviz estimate gives the mu_hat its row printed, 4.4978e-15."""
    terminate_after_stage_1(monkeypatch, stage=2)
    monkeypatch.chdir(tmp_path)
    code, err = cli_line(capsys, *SMALL_RUN, "--seed", "0", "--no-record", "--save-rollouts", "r.parquet")
    assert code == 143
    assert err.splitlines()[-1] == (
        "pemviz run: interrupted (SIGTERM); 3 stage(s) finished; rollouts r.parquet kept: stage 2, the last "
        "finished, 10 rollouts (mu_hat = 4.4978e-15, its row's estimate; pemviz estimate gives it back)"
    )
    assert cli.main(["estimate", "r.parquet", "--no-record"]) == 0
    assert "mu_hat = 4.4978e-15 (log mu_hat = -33.0352 nats)" in capsys.readouterr().out


# ------------------------------------------------------------------------------------------------ full disk


def test_disk_file_too_large_is_one_line_exit_1_and_leaves_the_old_file(tmp_path):
    """``ulimit -f 300`` (RLIMIT_FSIZE 300 KiB): the recording does not fit; it used to hang or trace back."""
    rrd = tmp_path / "f.rrd"
    rrd.write_bytes(OLD_RRD)
    limit = 300 * 1024
    proc = spawn(
        [*SMALL_RUN, "--save", rrd.name, "--overwrite"],
        tmp_path,
        preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit)),
    )
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 1, err[-2000:]
    assert "Traceback" not in err
    assert err.strip().splitlines()[-1] == "pemviz run: failed: cannot write: File too large; nothing partial was left"
    assert rrd.read_bytes() == OLD_RRD
    assert leftovers(tmp_path) == []


def test_disk_full_write_error_inside_atomic_write_leaves_nothing(tmp_path):
    target = tmp_path / "a.bin"
    target.write_bytes(b"old")

    def write(tmp: str) -> None:
        Path(tmp).write_bytes(b"partial")
        raise OSError(28, "No space left on device")

    with pytest.raises(OSError, match="No space left"):
        atomic_write(target, write)
    assert target.read_bytes() == b"old" and leftovers(tmp_path) == []


# ------------------------------------------------------------------------------------------- concurrent writers


@pytest.mark.parametrize("overwrite", [False, True])
def test_concurrent_writers_to_one_path_never_mix_and_never_share_a_temp_file(tmp_path, overwrite):
    target = tmp_path / "same.rrd"
    barrier = threading.Barrier(8)
    results: dict[int, str] = {}

    def writer(k: int) -> None:
        def write(tmp: str) -> None:
            barrier.wait()
            Path(tmp).write_bytes(b"RRF2" + bytes([k]) * 100_000)

        try:
            atomic_write(target, write, overwrite=overwrite)
            results[k] = "written"
        except OutputExists:
            results[k] = "refused"

    threads = [threading.Thread(target=writer, args=(k,)) for k in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    data = target.read_bytes()
    assert len(data) == 100_004 and len(set(data[4:])) == 1  # one writer's complete file
    winners = [k for k, r in results.items() if r == "written"]
    if not overwrite:
        assert winners == [data[4]]  # exactly the writer whose data is there reports success
    assert leftovers(tmp_path) == []


def test_concurrent_runs_with_one_save_path_one_wins_the_other_says_so(tmp_path):
    """Two RerunSinks to one path (two ``pemviz run --save same.rrd``): the second to finish is refused."""
    from pemviz.sinks.recording import RerunSink

    a, b = RerunSink.to_file(tmp_path / "same.rrd"), RerunSink.to_file(tmp_path / "same.rrd")
    assert a.close() == tmp_path / "same.rrd"
    first = (tmp_path / "same.rrd").read_bytes()
    with pytest.raises(OutputExists, match="appeared while this run worked"):
        b.close()
    assert (tmp_path / "same.rrd").read_bytes() == first and leftovers(tmp_path) == []


# ---------------------------------------------------------------------------------------------- sidecars

HOSTILE_SIDECARS = {
    "units-int": ({"units": 5}, "units must be a JSON object"),
    "units-values": ({"units": {"gap_m": 5}}, "units must map column names to unit text"),
    "provenance-int": ({"provenance": 5}, "provenance must be a JSON object"),
    "provenance-list": ({"provenance": [1, 2]}, "provenance must be a JSON object"),
    "signal-ranges-str": ({"signal_ranges": "x"}, "signal_ranges must be a JSON object"),
    "signal-ranges-bad": ({"signal_ranges": {"d": [3, 1]}}, "signal_ranges['d'] must be [lo, hi]"),
    "signals-list": ({"signals": ["d"]}, "signals must map STL names"),
    "obs-columns-str": ({"observation_columns": "gap_m"}, "observation_columns must be a list"),
    "window-str": ({"window_m": "ten"}, "window_m must be a number"),
    "window-negative": ({"window_m": -1}, "window_m must be a number of metres >= 0"),
    "n-rollouts-float": ({"n_rollouts": 2.5}, "n_rollouts must be an integer"),
    "n-steps-bool": ({"n_steps": True}, "n_steps must be an integer"),
    "pem-int": ({"pem": 5}, "pem must be a string"),
    "proposal-list": ({"proposal": ["x"]}, "proposal must be a string"),
    "version-str": ({"pemviz_version": 1}, "pemviz_version must be a string"),
    "dt-zero": ({"dt_s": 0}, "dt_s must be a number of seconds > 0"),
    "dt-str": ({"dt_s": "0.05"}, "dt_s must be a number of seconds > 0"),
    "formula-int": ({"formula": 5}, "formula must be STL text"),
    "formula-deep": ({"formula": "(" * 300 + "d >= 2" + ")" * 300}, "nested more than"),
    "formula-digits": ({"formula": "G[0,5](d >= ２)"}, "unexpected character"),
    "digest-short": ({"table_sha256": "abc"}, "table_sha256 must be a SHA-256"),
    "format-other": ({"format": "other"}, "format is 'other'"),
    "version-4": ({"version": 4}, "format version 4; this pemviz reads versions 1, 2, 3"),
    "weights-other": ({"weights": "half"}, "weights must be one of to-failure, full"),
    "stages-not-list": ({"stages": {"stage": 1}}, "stages must be a list of objects"),
    "stages-no-n": ({"stages": [{"stage": 1}]}, "stages[0] needs stage (an integer >= 0) and n"),
    "stages-components": (
        {"stages": [{"stage": 1, "n": 5, "components": [{"sampler": "q", "n": 4}]}]},
        "stages[0]: its components hold 4 rollouts, not n = 5",
    ),
    "stages-twice": ({"stages": [{"stage": 1, "n": 5}, {"stage": 1, "n": 5}]}, "stages lists stage 1 twice"),
    "stages-bound": ({"stages": [{"stage": 1, "n": 5, "max_weight": 0.5}]}, "max_weight must be a number >= 1"),
    "pooling-sum": ({"pooling": {"stages": [1, 2], "stage_weights": [0.5, 0.6]}}, "summing to 1"),
    "pooling-stages": ({"pooling": {"stages": [], "stage_weights": []}}, "pooling.stages must be a non-empty list"),
}


@pytest.mark.parametrize("case", list(HOSTILE_SIDECARS))
def test_sidecar_field_of_the_wrong_type_is_one_error_naming_file_and_field(tmp_path, case):
    change, message = HOSTILE_SIDECARS[case]
    side = tmp_path / "s.json"
    side.write_text(json.dumps({"formula": "G[0,5](d >= 2)", "dt_s": 0.05, **change}))
    with pytest.raises(rollout_format.RolloutFormatError) as err:
        rollout_format.read_sidecar(tmp_path / "s.parquet")
    assert str(err.value).startswith(f"{side}: ") and message in str(err.value)
    assert "\n" not in str(err.value) or case.startswith("formula")


@pytest.mark.parametrize(
    "body", ["[" * 100_000, "{}" * 3, '"x"', "\udcff", "null"], ids=["deep", "junk", "str", "bad-utf8", "null"]
)
def test_sidecar_that_is_not_a_json_object_is_one_error(tmp_path, body):
    side = tmp_path / "s.json"
    side.write_bytes(body.encode("utf-8", "surrogateescape"))
    with pytest.raises(rollout_format.RolloutFormatError, match=str(side)):
        rollout_format.read_sidecar(tmp_path / "s.parquet")


def test_sidecar_of_another_table_is_reported_as_an_incomplete_unit(tmp_path):
    """Killed between the Parquet and its sidecar: the new table beside the old sidecar is detected."""
    write_unit(tmp_path / "x.parquet", seed=0)
    side = rollout_format.sidecar_path(tmp_path / "x.parquet")  # x.rollouts.json
    old_side = side.read_bytes()
    write_unit(tmp_path / "x.parquet", seed=1)
    side.write_bytes(old_side)
    assert unit_state(tmp_path / "x.parquet") == "incomplete"


def test_sidecar_extreme_log_q_is_one_line_not_a_nan_crash(tmp_path, capsys):
    batch = small_batch()
    batch = RolloutBatch(
        batch.observations, batch.detected, batch.log_p, np.full(batch.log_q.shape, -1e308), batch.observation_names
    )
    rollout_writer.write_rollouts(tmp_path / "x.parquet", batch, braking_meta(formula="G[0,5](d >= 2)"))
    code, err = cli_line(capsys, "estimate", str(tmp_path / "x.parquet"), "--no-record")
    assert code == 2
    assert err == (
        f"pemviz estimate: error: {tmp_path / 'x.parquet'}: rollout 0: the importance log-weight "
        "sum(log_p - log_q) over its 5 steps is beyond float64 (+-1.8e308 nats; log_p down to -0.1, "
        "log_q down to -1e+308): no estimate can be formed from these log-probabilities"
    )


# ------------------------------------------------------------------------------------------ command line


def test_cli_bad_pem_or_seed_never_touches_an_existing_recording(tmp_path, capsys):
    keep = tmp_path / "keep.rrd"
    keep.write_bytes(OLD_RRD)
    code, err = cli_line(capsys, *SMALL_RUN, "--pem", "/etc/passwd", "--save", str(keep), "--overwrite")
    assert code == 2 and err.startswith("pemviz run: error: /etc/passwd: not a readable PEM file")
    code, err = cli_line(capsys, *SMALL_RUN, "--seed", str(2**64), "--save", str(keep), "--overwrite")
    assert code == 2 and err.startswith("pemviz run: error: --seed: seed = 18446744073709551616 is invalid")
    assert keep.read_bytes() == OLD_RRD and leftovers(tmp_path) == []


@pytest.mark.parametrize("command", ["run", "estimate"])
def test_cli_existing_save_is_refused_without_overwrite(tmp_path, capsys, command):
    keep = tmp_path / "keep.rrd"
    keep.write_bytes(OLD_RRD)
    args = [*SMALL_RUN] if command == "run" else ["estimate", str(tmp_path / "x.parquet")]
    code, err = cli_line(capsys, *args, "--save", str(keep))
    assert code == 2 and err == f"pemviz {command}: error: --save {keep}: exists; give --overwrite to replace it"
    assert keep.read_bytes() == OLD_RRD


def test_cli_save_rollouts_never_replaces_a_file_pemviz_did_not_write(tmp_path, capsys):
    (tmp_path / "x.rollouts.json").write_text('{"mine": true}')
    code, err = cli_line(
        capsys, *SMALL_RUN, "--no-record", "--save-rollouts", str(tmp_path / "x.parquet"), "--overwrite"
    )
    assert code == 2 and "x.rollouts.json: exists and is not a file pemviz wrote; not replacing it" in err
    (tmp_path / "other.rrd").write_text("not a recording")
    code, err = cli_line(capsys, *SMALL_RUN, "--save", str(tmp_path / "other.rrd"), "--overwrite")
    assert code == 2 and "other.rrd: exists and is not a .rrd file pemviz wrote" in err
    assert (tmp_path / "x.rollouts.json").read_text() == '{"mine": true}'


@pytest.mark.parametrize(
    "args, message",
    [
        (
            ["run", "--save-rollouts", "{tmp}/X.parquet", "--no-record"],
            "X.rollouts.json: exists and is not a regular file",
        ),
        (["run", "--save", "{tmp}/" + "a" * 240 + ".rrd"], "file name too long (244 bytes; at most 241 here)"),
        (["run", "--save-rollouts", "{tmp}/" + "b" * 232 + ".parquet", "--no-record"], "file name too long"),
        (
            ["pem", "eval", "--out", "{tmp}", "--save", "/proc/x.rrd"],
            "--save /proc/x.rrd: folder /proc is not writable",
        ),
        (["pem", "train", "--out", "/proc/x.pt"], "--out /proc/x.pt: folder /proc is not writable"),
        (["validate", "--out", "/proc/x"], "--out /proc/x: folder /proc is not writable"),
        (["tables", "--out", "/proc/x"], "--out /proc/x: folder /proc is not writable"),
        (["validate", "--out", "{tmp}/file.txt"], "exists and is not a folder"),
        (["run", "--k", "1", "--n", "1000000000000", "--no-record"], "this run needs about 518 TiB of memory"),
        (["run", "--n-final", "1000000000000", "--no-record"], "this run needs about 63.7 TiB of memory"),
        (["run", "--k", "1000000000000", "--no-record"], "--k: n_stages (K) = 1000000000000 is invalid"),
        (["run", "--ce-epochs", "1000000000000", "--no-record"], "--ce-epochs: ce_epochs = 1000000000000 is invalid"),
        (
            ["run", "--executor", "ray", "--ray-address", "127.0.0.1:1", "--no-record"],
            "--ray-address 127.0.0.1:1: cannot connect",
        ),
        (["run", "--executor", "ray", "--ray-address", "nonsense", "--no-record"], "use HOST:PORT"),
        (["serve", "--host", "999.1.1.1", "--port", "8791"], "--host '999.1.1.1': not an address or a name"),
        (["serve", "--host", "8.8.8.8", "--port", "8791"], "not an address of this machine"),
        (
            ["estimate", "{tmp}/run.rrd", "--no-record"],
            "run.rrd: a rerun recording, not a rollout file; `pemviz "
            "estimate` reads the Parquet rollout file that `pemviz run --save-rollouts NAME.parquet` writes",
        ),
        (
            ["estimate", "{tmp}/renamed.parquet", "--no-record"],
            "renamed.parquet: a rerun recording, not a rollout file",
        ),
        (["run", "--sigma", "high", "--no-record"], "argument --sigma: 'high' is not a number"),
        (["run", "--metric", "best", "--no-record"], "--metric: metric = 'best' is invalid: use one of classic, agm"),
        (["run", "--rel-error", "0", "--no-record"], "--rel-error: rel_error = 0.0 is invalid"),
        (
            ["run", "--max-time", "5", "--no-record"],
            "--max-time: max_time_s = 5.0 is invalid: a cap on the rollouts "
            "added for a target relative error or a requirement: give it with rel_error (--rel-error) or require "
            "(--require)",
        ),
        (
            ["run", "--margin", "-1", "--no-record"],
            "--margin: margin = -1.0 is invalid: the crash gap must be none or a number in [0, 10]",
        ),
        (
            ["run", "--scenario", "cut-in", "--margin", "1", "--no-record"],
            "--margin: margin = 1.0 is invalid: the " "crash gap is the braking scenario's",
        ),
        (["run", "--pem", "gbt", "--pem-uncertainty", "--no-record"], "ensemble_gbt.pt: no PEM ensemble there"),
        (["run", "--pem-shift", "11", "--no-record"], "--pem-shift: pem_shift = 11.0 is invalid"),
        (["report", "{tmp}/file.txt"], "file.txt: not a readable JSON file"),
    ],
    ids=[
        "json-folder",
        "name-240",
        "proposal-name",
        "pem-eval-proc",
        "pem-train-proc",
        "validate-proc",
        "tables-proc",
        "validate-file",
        "n-1e12",
        "n-final-1e12",
        "k-1e12",
        "epochs-1e12",
        "ray-refused",
        "ray-bad",
        "host-999",
        "host-foreign",
        "estimate-rrd",
        "estimate-rrd-renamed",
        "sigma-word",
        "metric-bad",
        "rel-error-0",
        "max-time-alone",
        "margin-negative",
        "margin-cut-in",
        "no-ensemble",
        "pem-shift-11",
        "report-not-json",
    ],
)
def test_cli_bad_output_or_resource_is_one_line_before_any_work(tmp_path, capsys, args, message):
    (tmp_path / "X.rollouts.json").mkdir()
    (tmp_path / "file.txt").write_text("x")
    for name in ("run.rrd", "renamed.parquet"):  # what a rerun recording starts with
        (tmp_path / name).write_bytes(b"RRF2\x00\x29\x00\x00")
    if "ray" in args and __import__("importlib").util.find_spec("ray") is None:
        pytest.skip("Ray is not installed")
    before = sorted(p.name for p in tmp_path.iterdir())
    t0 = time.perf_counter()
    code, err = cli_line(capsys, *[a.replace("{tmp}", str(tmp_path)) for a in args])
    assert code == 2 and len(err.splitlines()) == 1 and message in err, err
    assert time.perf_counter() - t0 < 60  # refused before the work, not after it
    assert sorted(p.name for p in tmp_path.iterdir()) == before


def test_cli_a_folder_named_like_an_old_temp_file_does_not_block_a_run(tmp_path, capsys):
    (tmp_path / "f.rrd.partial").mkdir()
    code, err = cli_line(capsys, *SMALL_RUN, "--save", str(tmp_path / "f.rrd"))
    assert code == 0, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f.result.json", "f.rrd", "f.rrd.partial"]


def test_cli_serve_on_every_interface_warns_that_the_panel_has_no_authentication(capsys, monkeypatch):
    import pemviz.app.panel as panel

    monkeypatch.setattr(panel, "serve", lambda *a, **k: None)
    for host in ("0.0.0.0", ""):
        code, err = cli_line(capsys, "serve", "--host", host, "--port", "0")
        assert code == 0
        assert err.splitlines()[0].startswith(
            f"pemviz serve: warning: --host {host!r} is reachable from other "
            "machines and the panel has no authentication"
        )
    code, err = cli_line(capsys, "serve", "--host", "127.0.0.1", "--port", "0")
    assert code == 0 and "warning" not in err


def test_cli_jobs_beyond_the_cpu_count_are_capped_with_a_message():
    from pemviz.engine.resources import cap_jobs, usable_cpus

    said: list[str] = []
    assert cap_jobs(1000, said.append) == usable_cpus()
    assert said == [
        f"--jobs 1000: this machine gives {usable_cpus()} CPU{'s' * (usable_cpus() != 1)}; using "
        f"{usable_cpus()} worker processes"
    ]
    assert cap_jobs(1, said.append) == 1 and len(said) == 1


# ------------------------------------------------------------------------------------------ writer primitives


def test_writer_check_output_path_refuses_special_files_and_symlinks(tmp_path):
    (tmp_path / "link.rrd").symlink_to("/etc/passwd")
    with pytest.raises(ValueError, match="not a regular file"):
        check_output_path(tmp_path / "link.rrd", ".rrd", "--save", overwrite=True)
    os.mkfifo(tmp_path / "fifo.rrd")
    with pytest.raises(ValueError, match="not a regular file"):
        check_output_path(tmp_path / "fifo.rrd", ".rrd", overwrite=True)


def test_writer_interrupt_inside_a_write_removes_the_temp_file_and_keeps_the_old_one(tmp_path):
    target = tmp_path / "a.bin"
    target.write_bytes(b"old")

    def write(tmp: str) -> None:
        Path(tmp).write_bytes(b"half")
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        atomic_write(target, write)
    assert target.read_bytes() == b"old" and leftovers(tmp_path) == []


def test_a_rollout_sidecar_has_a_name_of_its_own_and_an_old_one_still_reads(tmp_path):
    # r.parquet's sidecar is r.rollouts.json, so `--json r.json` (the README's name for a result) no longer collides
    assert rollout_format.sidecar_path(tmp_path / "r.parquet") == tmp_path / "r.rollouts.json"
    write_unit(tmp_path / "r.parquet", seed=0)
    new = json.loads((tmp_path / "r.rollouts.json").read_text())
    assert not (tmp_path / "r.json").exists() and rollout_format.read_sidecar(tmp_path / "r.parquet").formula
    # a file written before: its sidecar r.json beside it reads the same
    (tmp_path / "r.rollouts.json").rename(tmp_path / "r.json")
    assert rollout_format.existing_sidecar(tmp_path / "r.parquet") == tmp_path / "r.json"
    assert rollout_format.read_sidecar(tmp_path / "r.parquet").formula == new["formula"]
