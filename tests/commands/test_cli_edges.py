"""Edges of the command line a user meets: a typo in a flag gets the nearest known one, the recorded command pastes
back into a shell as it was typed, and `pemviz serve` refuses a bad PEM before it serves."""

from __future__ import annotations

import json
import shlex

from conftest import run_cli


def test_an_unknown_flag_gets_the_nearest_known_one_in_one_line(tmp_path):
    proc = run_cli("run", "--rel-eror", "0.1", "--no-record", cwd=tmp_path)
    assert proc.returncode == 2 and proc.stdout == ""
    assert proc.stderr.strip().splitlines() == [
        "pemviz: error: unrecognized arguments: --rel-eror 0.1; --rel-eror: did you mean --rel-error?"
    ]
    two = run_cli("run", "--seeed", "3", "--requre", "p < 1e-9", cwd=tmp_path)
    assert two.returncode == 2 and "--seeed: did you mean --seed?; --requre: did you mean --require?" in two.stderr
    far = run_cli("run", "--zzzz", "1", cwd=tmp_path)  # nothing near it: no suggestion
    assert far.returncode == 2 and "did you mean" not in far.stderr
    assert not any(tmp_path.iterdir())  # nothing written


def test_the_recorded_command_is_quoted_for_a_shell(tmp_path):
    args = [
        "run",
        "--k",
        "3",
        "--n",
        "100",
        "--n-final",
        "200",
        "--no-record",
        "--require",
        "p < 1e-10",
        "--max-sims",
        "600",
        "--json",
        "r.json",
    ]
    proc = run_cli(*args, cwd=tmp_path)
    assert proc.returncode in (1, 3), proc.stderr[-2000:]
    command = json.loads((tmp_path / "r.json").read_text())["command"]
    assert "'p < 1e-10'" in command  # pasted, `<` is no redirect
    assert shlex.split(command) == ["pemviz", *args]


def test_serve_refuses_an_unreadable_pem_before_it_serves(tmp_path):
    (tmp_path / "empty.pt").write_bytes(b"")
    proc = run_cli("serve", "--pem", "empty.pt", "--port", "0", cwd=tmp_path, timeout=60)
    assert proc.returncode == 2 and "open http" not in proc.stdout
    assert proc.stderr.strip().splitlines() == [
        "pemviz serve: error: empty.pt: not a readable PEM file (it is empty): give a PEM file pemviz wrote "
        "(pemviz pem train, save_pem) or a shipped PEM (gbt, ml-nn)"
    ]


def test_an_unwritable_folder_says_read_only_not_errno_s_contradiction(tmp_path):
    # /proc refuses a new file with ENOENT, whose words "No such file or directory" contradict "folder /proc"
    proc = run_cli("run", "--save", "/proc/x.rrd", cwd=tmp_path)
    assert proc.returncode == 2
    assert proc.stderr.strip() == "pemviz run: error: --save /proc/x.rrd: folder /proc is not writable (read-only)"


def test_a_report_named_after_its_result_says_so_when_it_exists(tmp_path):
    proc = run_cli("run", "--no-record", "--k", "2", "--n", "50", "--n-final", "50", "--json", "b.json", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    (tmp_path / "b.html").write_text("mine")
    again = run_cli("report", "b.json", cwd=tmp_path)
    assert again.returncode == 2 and "--out b.html" not in again.stderr  # no --out was given
    assert again.stderr.strip() == (
        "pemviz report: error: the report (named after its result; --out names another) "
        "b.html: writes b.html and its Markdown twin b.md; b.html exists: give --overwrite to replace it"
    )
    assert (tmp_path / "b.html").read_text() == "mine"


def test_an_interrupt_after_the_run_names_the_files_it_had_written(tmp_path, monkeypatch, capsys):
    # Ctrl-C while the result files are made: the rollouts are already written, and the line says so (it said
    # "nothing written")
    import pemviz.commands.run as run_command
    from pemviz.cli import main

    def interrupt(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(run_command, "result_lines", interrupt)
    monkeypatch.chdir(tmp_path)
    code = main(
        [
            "run",
            "--k",
            "2",
            "--n",
            "50",
            "--n-final",
            "50",
            "--no-record",
            "--save-rollouts",
            "r.parquet",
            "--json",
            "r.json",
        ]
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 130 and (tmp_path / "r.parquet").is_file() and not (tmp_path / "r.json").exists()
    assert err[-1] == (
        "pemviz run: interrupted (Ctrl-C); the run finished; r.parquet, r.rollouts.json written; its "
        "result files not written"
    )
