"""The user guide builds with ``mkdocs build --strict`` and its command-line reference covers every command."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys

import pytest

from conftest import REPO

needs_mkdocs = pytest.mark.skipif(
    importlib.util.find_spec("mkdocs") is None or importlib.util.find_spec("mkdocstrings") is None,
    reason='the docs extra is not installed (pip install -e ".[docs]")',
)


@needs_mkdocs
def test_user_guide_builds_strict_with_every_command_in_the_cli_reference(tmp_path) -> None:
    env = {**os.environ, "PYTHONPATH": str(REPO), "NO_MKDOCS_2_WARNING": "1"}
    proc = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
                          cwd=REPO, env=env, capture_output=True, text=True, timeout=600)  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    cli = (tmp_path / "site" / "cli" / "index.html").read_text()
    for command in ("run", "data fetch", "pem train", "pem eval", "serve", "estimate", "validate", "tables"):
        assert f"pemviz {command}" in cli, command
    assert "--grpc-port" in cli and "&lt;!-- pemviz-cli --&gt;" not in cli and "<!-- pemviz-cli -->" not in cli
    assert "Any Python simulator plugs into the sampler" in (tmp_path / "site" / "own-simulator" / "index.html").read_text()
