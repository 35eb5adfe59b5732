"""``pemviz run``'s recording flags (rerun's standard ``--save/--serve/--connect/--stdout/--headless``),
the default recording name and the files a run says it wrote."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from datetime import datetime
from pathlib import Path

import pytest
from pemviz.cli import main as cli_main
from pemviz.commands.run_recording import default_recording_path, web_viewer_url
from pemviz.config import ExperimentConfig

from conftest import REPO

QUICK = ("--preset", "quick", "--k", "2")


def pemviz(*args: str, cwd: Path, timeout: float = 300, **kw) -> subprocess.CompletedProcess:
    """This checkout's ``pemviz`` (PYTHONPATH), run in ``cwd``."""
    env = {**os.environ, "PYTHONPATH": str(REPO), "RERUN_ANALYTICS": "false"}
    return subprocess.run(
        [sys.executable, "-m", "pemviz.cli", *args],
        cwd=cwd,
        env=env,
        timeout=timeout,
        capture_output=True,
        **({"text": True} | kw),
    )


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize(
    ("flags", "named"),
    [
        (("--no-record", "--save", "x.rrd"), "--save and --no-record"),
        (("--serve", "--save", "x.rrd"), "--save and --serve"),
        (("--stdout", "--connect"), "--connect and --stdout"),
        (("--grpc-port", "5000"), "--grpc-port 5000: only with --serve"),
        (("--connect", "notaurl"), "--connect notaurl: not a rerun viewer URL"),
        (("--url", "http://127.0.0.1:9876"), "not a rerun viewer URL"),
    ],
)
def test_bad_recording_flags_give_one_line_and_exit_2_before_any_work(tmp_path, monkeypatch, capsys, flags, named):
    monkeypatch.chdir(tmp_path)
    assert cli_main(["run", *QUICK, *flags]) == 2
    out, err = capsys.readouterr()
    assert err.count("\n") == 1 and named in err, err
    assert out == "" and list(tmp_path.iterdir()) == []


def test_connect_to_a_port_where_no_viewer_listens_fails_fast_with_one_line(tmp_path, monkeypatch, capsys) -> None:
    monkeypatch.chdir(tmp_path)
    url = f"rerun+http://127.0.0.1:{free_port()}/proxy"
    start = time.monotonic()
    assert cli_main(["run", *QUICK, "--connect", url]) == 2
    assert time.monotonic() - start < 30
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"--connect {url}: no rerun viewer there" in err, err
    assert list(tmp_path.iterdir()) == []


def test_serve_prints_both_addresses_and_keeps_serving_after_the_run_until_ctrl_c(tmp_path: Path) -> None:
    grpc_port, web_port = free_port(), free_port()
    env = {**os.environ, "PYTHONPATH": str(REPO), "RERUN_ANALYTICS": "false"}
    argv = [
        sys.executable,
        "-m",
        "pemviz.cli",
        "run",
        *QUICK,
        "--serve",
        "--headless",
        "--grpc-port",
        str(grpc_port),
        "--web-port",
        str(web_port),
    ]
    proc = subprocess.Popen(argv, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        lines = []
        deadline = time.monotonic() + 240
        while time.monotonic() < deadline:  # stderr is line-buffered; each line arrives as it is printed
            line = proc.stderr.readline()
            if not line:
                break
            lines.append(line)
            if "still serving" in line:
                break
        err = "".join(lines)
        assert "still serving" in err, err
        grpc_url = f"rerun+http://127.0.0.1:{grpc_port}/proxy"
        assert f"serving at {grpc_url}" in err and web_viewer_url(grpc_url, web_port) in err
        assert proc.poll() is None  # the run is over, the process still serves
        socket.create_connection(("127.0.0.1", grpc_port), timeout=5).close()
        with urllib.request.urlopen(f"http://127.0.0.1:{web_port}/", timeout=10) as page:
            assert page.status == 200
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=60) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert list(tmp_path.iterdir()) == []  # serving writes no file


def test_stdout_streams_a_recording_and_moves_the_table_to_stderr(tmp_path: Path) -> None:
    proc = pemviz("run", *QUICK, "--stdout", cwd=tmp_path, text=False)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout[:4] == b"RRF2" and len(proc.stdout) > 10_000  # rerun's .rrd stream
    assert b"mu_hat = " in proc.stderr and list(tmp_path.iterdir()) == []


def test_default_recording_name_says_what_ran_and_every_written_file_is_printed(tmp_path: Path) -> None:
    small = ("--k", "2", "--n", "50", "--n-final", "50", "--ce-epochs", "5")  # the paper's proposal is saved too
    proc = pemviz(
        "run",
        "--preset",
        "paper",
        *small,
        "--metric",
        "agm",
        "--seed",
        "3",
        "--save-rollouts",
        "r.parquet",
        cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert len(list((tmp_path / "recordings").iterdir())) == 2  # the recording and its result document
    (rrd,) = (tmp_path / "recordings").glob("*.rrd")
    assert rrd.name.startswith("braking-adaptive-paper-agm-batched-seed3-") and rrd.suffix == ".rrd"
    named = dict(
        line.split(": ", 1)
        for line in proc.stderr.splitlines()
        if line.startswith(("recording: ", "rollouts: ", "rollouts' ", "result: "))
    )
    beside = "recordings/" + rrd.name.removesuffix(".rrd") + ".result.json"  # the run's result document
    assert named == {  # each file named for what it is: the Parquet table as the rollouts, the JSON as its sidecar
        "recording": "recordings/" + rrd.name,
        "result": beside,
        "rollouts": "r.parquet",
        "rollouts' sidecar": "r.rollouts.json",
        "rollouts' proposal": "r.proposal.pt",
    }
    written = {p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*") if p.is_file()}
    assert written == set(named.values())


def test_default_recording_names_never_collide(tmp_path: Path) -> None:
    cfg = ExperimentConfig.of()
    first = default_recording_path(cfg, "state-ce", tmp_path)
    first.write_bytes(b"x")
    second = default_recording_path(cfg, "state-ce", tmp_path)
    assert second != first and second.name.endswith("-2.rrd")
    stamp = f"{datetime.now():%Y%m%d}"
    assert first.name.startswith(f"braking-adaptive-state-ce-{cfg.metric}-{cfg.sim}-seed{cfg.seed}-{stamp}")
