"""Output folders behave alike: ``validate`` and ``tables`` keep each finished run and resume from ``--out``;
``pem eval --out`` creates its folder as they do; the default output folders are ignored by git."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from pemviz.cli import main as cli_main
from pemviz.commands import UsageError, output_folder
from pemviz.studies.validation import RUNS_FILE

from conftest import REPO, SHARED

TINY = (
    "--problems",
    "toy-1e-3",
    "--presets",
    "paper",
    "--baselines",
    "mc",
    "--k",
    "2",
    "--ce-epochs",
    "20",
    "--pretrain-epochs",
    "20",
)


def runs(folder: Path) -> list[dict]:
    return [json.loads(line) for line in (folder / RUNS_FILE).read_text().splitlines()]


def test_validate_keeps_every_run_and_a_larger_run_resumes_from_them(tmp_path: Path, capsys) -> None:
    out = tmp_path / "new" / "v"  # created, parents too
    assert cli_main(["validate", *TINY, "--seeds", "2", "--out", str(out)]) == 0
    first = runs(out)
    assert sorted((r["record"]["method"], r["record"]["seed"]) for r in first) == [
        ("adaptive (paper)", 0),
        ("adaptive (paper)", 1),
        ("mc", 0),
        ("mc", 1),
    ]
    capsys.readouterr()
    with (out / RUNS_FILE).open("a") as f:  # a run killed while its line was being written
        f.write('{"job": "torn')
    assert cli_main(["validate", *TINY, "--seeds", "3", "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert f"resuming: 4 of 6 runs already in {out / RUNS_FILE}" in err
    assert "seed 0:" not in err and "seed 1:" not in err and err.count("seed 2:") == 2  # only the new runs ran
    second = runs(out)  # the torn line is gone; the first four lines are untouched
    assert second[:4] == first and len(second) == 6
    assert "[6/6 runs" in err  # progress with elapsed time and ETA (stderr is not a terminal here)


def test_validate_killed_by_sigterm_keeps_its_finished_runs_for_the_next_call(tmp_path: Path) -> None:
    out = tmp_path / "v"
    argv = [sys.executable, "-m", "pemviz.cli", "validate", *TINY, "--baselines", "", "--seeds", "6", "--out", str(out)]
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen(argv, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 240
        while time.monotonic() < deadline and proc.poll() is None:  # wait for the first finished run
            if (out / RUNS_FILE).is_file() and (out / RUNS_FILE).read_text().count("\n") >= 1:
                break
            time.sleep(0.2)
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    kept = len(runs(out))
    assert kept >= 1
    again = subprocess.run(argv, env=env, capture_output=True, text=True, timeout=600)
    assert again.returncode == 0, again.stderr[-2000:]
    if kept < 6:
        assert f"resuming: {kept} of 6 runs" in again.stderr
    assert len(runs(out)) == 6


def test_tables_resume_from_their_out_folder(tmp_path: Path, capsys) -> None:
    args = [
        "tables",
        "--problem",
        "toy-1e-3",
        "--reps",
        "2",
        "--k",
        "2",
        "--ce-epochs",
        "20",
        "--pretrain-epochs",
        "20",
        "--extra",
        "",
        "--mc-large",
        "200",
        "--naive-large",
        "100",
        "--jobs",
        "1",
        "--no-record",
        "--out",
        str(tmp_path / "t"),
    ]
    assert cli_main(args) == 0
    table = (tmp_path / "t" / "tables.csv").read_text()
    n = len(runs(tmp_path / "t"))
    capsys.readouterr()
    assert cli_main(args) == 0
    assert f"resuming: {n} of {n} runs" in capsys.readouterr().err
    assert (tmp_path / "t" / "tables.csv").read_text() == table  # the same runs, the same table


def test_output_folder_creates_parents_and_refuses_a_file(tmp_path: Path) -> None:
    assert output_folder(tmp_path / "a" / "b").is_dir()
    (tmp_path / "f").write_text("x")
    with pytest.raises(UsageError, match="exists and is not a folder"):
        output_folder(tmp_path / "f")


@pytest.mark.skipif(not (SHARED / "data" / "kitti-salient").is_dir(), reason="KITTI salient files absent")
def test_pem_eval_creates_its_out_folder_like_the_other_commands(tmp_path: Path) -> None:
    out = tmp_path / "new" / "eval"
    assert cli_main(["pem", "eval", "--quick", "--models", "guess-mu", "--no-record", "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["pem-eval.csv", "pem-eval.md"]


@pytest.mark.parametrize("path", ["recordings/x.rrd", "tables/tables.csv", "validate/runs.jsonl", "x.rrd"])
def test_default_outputs_are_ignored_by_git(path: str) -> None:
    if not (REPO / ".git").exists():
        pytest.skip("not a git checkout")
    proc = subprocess.run(["git", "check-ignore", "-q", path], cwd=REPO, timeout=30)
    assert proc.returncode == 0, f"{path} is not ignored by git"
