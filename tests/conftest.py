"""Shared fixtures: repository paths, the shared data folder, and a helper to run the CLI."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"

os.environ.setdefault("RERUN_ANALYTICS", "false")
torch.set_num_threads(1)  # pemviz's networks are tiny: a second thread only adds contention on 2 cores


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    if not SHARED.is_dir():
        pytest.skip(f"shared folder {SHARED} is absent (it sits beside the repository in CI)")
    return SHARED


def run_cli(*args: str, cwd: Path | None = None, timeout: float = 600) -> subprocess.CompletedProcess:
    """Run ``python -m pemviz.cli ARGS`` and capture its output."""
    return subprocess.run(
        [sys.executable, "-m", "pemviz.cli", *args],
        cwd=cwd or REPO,
        capture_output=True,
        text=True,
        timeout=timeout,
    )
