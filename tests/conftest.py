"""Shared fixtures: repository paths, the shared data folder, and a helper to run the CLI."""

from __future__ import annotations

import importlib.util
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from pemviz.engine.resources import ONE_THREAD_ENV
from threadpoolctl import threadpool_limits

REPO = Path(__file__).resolve().parents[1]


def load_script(path: Path):
    """The Python file ``path`` (a benchmark or a script outside the package) imported as a module named after its
    stem, registered in ``sys.modules`` (dataclasses look their module up there while a class is built)."""
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


SHARED = REPO.parent / "shared"

os.environ.setdefault("RERUN_ANALYTICS", "false")
torch.set_num_threads(1)  # pemviz's networks are tiny: a second thread only adds contention on 2 cores
# One BLAS / OpenMP thread in each test process and in the commands the tests start. Idle OpenBLAS threads spin, and
# the README's test command runs two test processes on the 2-core machine beside the commands they start: measured
# there on test_severity.py, test_pem_uncertainty.py and test_engine.py under ``-n 2``, 220 s with numpy's default
# threads and 82 s with one. No number depends on it: a seed gives the same run on any thread count.
for _variable, _value in ONE_THREAD_ENV.items():
    os.environ.setdefault(_variable, _value)
threadpool_limits(1)
# Ctrl-C as in a terminal: a shell starts a background job without job control (``nohup pytest ... &`` in a script)
# with SIGINT ignored, the commands the tests start would inherit that, and the tests that stop a server with Ctrl-C
# would wait on it until their timeouts.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    if not SHARED.is_dir():
        pytest.skip(f"shared folder {SHARED} is absent (it sits beside the repository in CI)")
    return SHARED


BIN = Path(sys.executable).parent
"""The running environment's scripts folder: commands a test runs (``rerun``, ``pemviz``) are taken from here, not from
``PATH``, so ``venv/bin/python -m pytest`` without an activated environment finds them."""


def verify_rrd(path: Path, timeout: float = 300) -> None:
    """Assert that ``rerun rrd verify`` (the pinned rerun-sdk's own checker) accepts the recording at ``path``."""
    proc = subprocess.run(
        [str(BIN / "rerun"), "rrd", "verify", str(path)],
        capture_output=True,
        text=True,
        timeout=timeout,
        env={**os.environ, "RERUN_ANALYTICS": "false"},
    )
    assert proc.returncode == 0, proc.stderr[-2000:]


def run_cli(*args: str, cwd: Path | None = None, timeout: float = 600) -> subprocess.CompletedProcess:
    """Run ``python -m pemviz.cli ARGS`` and capture its output."""
    return subprocess.run(
        [sys.executable, "-m", "pemviz.cli", *args],
        cwd=cwd or REPO,
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def estimated_log_mu(path: Path) -> float:
    """log mu_hat (nats, full float64) of a ``pemviz estimate --json PATH`` document: its ``log_p``; -inf where it is
    null with p = 0 (no failure weighs anything), nan where both are null."""
    import json
    import math

    e = json.loads(Path(path).read_text())["estimate"]
    if e["log_p"] is not None:
        return float(e["log_p"])
    return -math.inf if e["p"] == 0.0 else math.nan


def doc_python_block(page: str, heading: str) -> str:
    """The first python code block under ``heading`` (a whole heading line, e.g. ``## An example``) of the user guide's
    ``docs/<page>``: the guide's examples are run by tests as written."""
    text = (REPO / "docs" / page).read_text()
    assert heading in text, f"docs/{page}: no heading {heading!r}"
    block = re.search(r"```python\n(.*?)```", text.split(heading, 1)[1], re.S)
    assert block, f"docs/{page}: no python block under {heading!r}"
    return block.group(1)


def float64_network(layers, x):
    """Folded affine layers ``(W [out, in], b [out])`` in plain float64 products, ReLU between: the reference the
    PEMs' order-free grid form (pemviz.pem.network.GridMLP) is compared with. float64 [N, out] of inputs [N, in]."""
    h = x
    for i, (w, b) in enumerate(layers):
        h = h @ w.T + b
        if i < len(layers) - 1:
            h = np.maximum(h, 0.0)
    return h


def result_schema() -> dict:
    """The result document's JSON schema, as docs/ci.md gives it."""
    import json

    text = (REPO / "docs" / "ci.md").read_text()
    return json.loads(re.search(r"<!-- result schema -->\n```json\n(.*?)```", text, re.S).group(1))


PLUGIN_SCENARIO_HEADING = "### A scenario package: one module, one registration"
"""The heading of the guide's scenario module (docs/own-simulator.md)."""


@pytest.fixture
def defensive_mc(monkeypatch):
    """The guide's method of one's own (``tests/estimators/user_method.py``, ``defensive-mc``, two settings),
    imported (so registered) for this test only."""
    from pemviz.methods import unregister_method

    monkeypatch.syspath_prepend(str(REPO / "tests" / "estimators"))
    sys.modules.pop("user_method", None)
    __import__("user_method")
    yield sys.modules["user_method"]
    unregister_method("defensive-mc")
    sys.modules.pop("user_method", None)
