"""The research studies' tests (``python -m pytest research/tests``; pyproject's ``testpaths = ["tests"]`` keeps them
out of the README's test command).

They import ``REPO`` and ``load_script`` from ``conftest`` as the tests under ``tests/`` do: this file lends them
those of ``tests/conftest.py`` (with its one-thread settings), imported under another module name since this file is
itself the module ``conftest`` here."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

_TESTS_CONFTEST = Path(__file__).resolve().parents[2] / "tests" / "conftest.py"
_spec = importlib.util.spec_from_file_location("pemviz_tests_conftest", _TESTS_CONFTEST)
_shared = importlib.util.module_from_spec(_spec)
sys.modules[_spec.name] = _shared
_spec.loader.exec_module(_shared)

REPO = _shared.REPO
load_script = _shared.load_script
