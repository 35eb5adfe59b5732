"""``pemviz serve`` as a command: binds 127.0.0.1 by default, serves the page, stops on Ctrl-C."""

from __future__ import annotations

import queue
import re
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

import pytest

from conftest import REPO, run_cli


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def listening_addresses(port: int) -> set[str]:
    """Local IPv4 addresses with a listening TCP socket on ``port`` (Linux /proc/net/tcp, state 0A)."""
    found = set()
    for line in Path("/proc/net/tcp").read_text().splitlines()[1:]:
        local, _, state = line.split()[1:4]
        addr, port_hex = local.split(":")
        if state == "0A" and int(port_hex, 16) == port:
            found.add(socket.inet_ntoa(bytes.fromhex(addr)[::-1]))
    return found


@pytest.mark.skipif(not Path("/proc/net/tcp").exists(), reason="needs Linux /proc/net/tcp")
def test_serve_binds_localhost_only_serves_the_page_and_stops_on_ctrl_c(tmp_path):
    port = free_port()
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "pemviz.cli",
            "serve",
            "--port",
            str(port),
            "--preset",
            "quick",
            "--recordings",
            str(tmp_path / "rec"),
        ],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        lines: queue.Queue[str] = queue.Queue()
        threading.Thread(target=lambda: [lines.put(x) for x in proc.stdout], daemon=True).start()
        bound, seen, deadline = None, [], time.monotonic() + 120
        while bound is None and time.monotonic() < deadline and proc.poll() is None:
            try:
                seen.append(lines.get(timeout=0.5))
            except queue.Empty:
                continue
            m = re.search(r"open http://127\.0\.0\.1:(\d+) ", seen[-1])  # printed once the server listens
            bound = int(m.group(1)) if m else None
        assert bound is not None, ("".join(seen), proc.stderr.read() if proc.poll() is not None else "")
        assert listening_addresses(bound) == {"127.0.0.1"}
        with urllib.request.urlopen(f"http://127.0.0.1:{bound}/", timeout=10) as resp:
            assert resp.status == 200 and b"<html" in resp.read(2000).lower()
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=20) == 0
        assert listening_addresses(bound) == set()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stdout.close()
        proc.stderr.close()


def test_serve_rejects_an_unknown_preset_in_one_line():
    proc = run_cli("serve", "--preset", "nope", "--port", "0", timeout=120)
    assert proc.returncode == 2
    assert (
        "pemviz serve: error: --preset 'nope' is invalid: use one of state-ce, paper, authors-code, quick"
        in proc.stderr
    )
