"""The built wheel is a working install: PEM weights inside, `pemviz run` from an empty folder elsewhere.

Builds the wheel from a copy of the sources (the checkout is left untouched), installs it non-editable
into a fresh virtual environment (no system site-packages), then lets that environment borrow the running
environment's site-packages for the heavy dependencies (torch, rerun) through a ``.pth`` file, and checks that the
``pemviz`` that runs is the wheel's, not the checkout or an editable install. This works from any interpreter: a
user's virtual environment (whose packages ``--system-site-packages`` would not see) as well as a system Python.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    src = tmp_path_factory.mktemp("src")
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(REPO / name, src / name)
    shutil.copytree(REPO / "pemviz", src / "pemviz", ignore=shutil.ignore_patterns("__pycache__"))
    out = tmp_path_factory.mktemp("wheelhouse")
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", str(src), "-w", str(out)],
        check=True,
        cwd=src,
        timeout=300,
    )
    (whl,) = out.glob("pemviz-*.whl")
    return whl


def test_wheel_holds_the_shipped_pems_and_their_readme(wheel: Path) -> None:
    import pemviz

    assert wheel.name.startswith(f"pemviz-{pemviz.__version__}-")  # one source for the version
    names = set(zipfile.ZipFile(wheel).namelist())
    assert {"pemviz/assets/pem_ml-nn.pt", "pemviz/assets/pem_gbt.pt", "pemviz/assets/README.md"} <= names


@pytest.mark.slow
def test_pemviz_run_from_the_installed_wheel_in_an_empty_folder(wheel: Path, tmp_path: Path) -> None:
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=300)
    py = venv / "bin" / "python"
    subprocess.run(
        [str(py), "-m", "pip", "install", "-q", "--no-deps", "--no-index", str(wheel)], check=True, timeout=300
    )
    # Only now (pip must not see, and so not uninstall, the running environment's pemviz): the running environment's
    # site-packages folders, after the new one's own. Their .pth files (an editable pemviz's among them) are not run.
    borrowed = [p for p in sys.path if Path(p).name in ("site-packages", "dist-packages") and Path(p).is_dir()]
    own = subprocess.run(
        [str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
        capture_output=True,
        text=True,
        check=True,
        timeout=60,
    ).stdout.strip()
    (Path(own) / "borrowed-from-the-test-environment.pth").write_text("\n".join(borrowed) + "\n")
    work = tmp_path / "empty"
    work.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PEMVIZ_ASSETS_DIR")}
    env["RERUN_ANALYTICS"] = "false"
    where = subprocess.run(
        [str(py), "-c", "import pemviz, pemviz.pem.store as p; print(pemviz.__file__); print(p.assets_dir())"],
        cwd=work,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    installed = sorted(p.name for p in Path(own).iterdir())
    assert where.returncode == 0, f"{where.stderr[-2000:]}\n{own} holds: {installed}"  # what failed, if it does
    module_file, assets = where.stdout.split()
    assert Path(module_file).is_relative_to(venv), module_file  # the wheel's pemviz, not the checkout
    assert Path(assets).is_relative_to(venv) and (Path(assets) / "pem_ml-nn.pt").is_file()
    proc = subprocess.run(
        [str(venv / "bin" / "pemviz"), "run", "--no-record", "--preset", "quick", "--k", "2"],
        cwd=work,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    found = re.search(r"mu_hat = ([0-9.e+-]+) ", proc.stdout)
    assert found and 1e-16 < float(found.group(1)) < 1e-13, proc.stdout[-2000:]  # the crash probability ~2e-15
    assert list(work.iterdir()) == []  # --no-record writes nothing
